"""The embedded PostgreSQL cluster: private to one cell, in var/pg, listening on a unix socket in
var/run/pg (and on its host's address in a cell spread over several hosts: gwc.db.access). Made by
initdb the first time, started and stopped with pg_ctl, as the postgres OS user when we are root."""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import pwd
import shutil
import stat
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import psycopg
from psycopg import sql

from gwc import hostuser
from gwc.budget import MAX_CONNECTIONS
from gwc.config import Config
from gwc.db.access import lot_access, make_certificate, uses_tls, write_hba
from gwc.db.names import DB_NAME, SOCKET_MAX, SUPERUSER, db_port, socket_dir, socket_path
from gwc.errors import DatabaseError
from gwc.private import PG_OS_USER, open_lock, private_dir, secure_var, traversable_by

INSTALL_HINT = "install the PostgreSQL server (Debian/Ubuntu: `apt-get install postgresql`)"

# Settings of the embedded cluster. Durability stays at PostgreSQL's defaults; the cell's many
# module processes each hold a connection, hence max_connections. etc/cell.toml [database.settings]
# adds to or overrides these (tests turn fsync off there).
DEFAULT_SETTINGS: dict[str, Any] = {
    "max_connections": MAX_CONNECTIONS,
    "shared_buffers": "64MB",
    "unix_socket_permissions": "0700",
}

_log = logging.getLogger("gwc.db")


# ----------------------------------------------------------------------------- binaries


def find_pg_bin(name: str) -> Path:
    """Find a PostgreSQL program: PATH, then `pg_config --bindir`, then the newest /usr/lib/postgresql."""
    found = shutil.which(name)
    if found:
        return Path(found)
    candidates: list[Path] = []
    pg_config = shutil.which("pg_config")
    if pg_config:
        with contextlib.suppress(OSError, subprocess.SubprocessError):
            out = subprocess.run([pg_config, "--bindir"], capture_output=True, text=True, timeout=10)
            if out.returncode == 0 and out.stdout.strip():
                candidates.append(Path(out.stdout.strip()))
    versions = []
    with contextlib.suppress(OSError):
        for d in Path("/usr/lib/postgresql").iterdir():
            if d.name.replace(".", "").isdigit():
                versions.append(d)
    versions.sort(key=lambda d: [int(x) for x in d.name.split(".")], reverse=True)
    candidates += [d / "bin" for d in versions]
    for bindir in candidates:
        path = bindir / name
        if os.access(path, os.X_OK):
            return path
    raise DatabaseError(
        f"PostgreSQL program {name!r} not found on PATH, via pg_config or in /usr/lib/postgresql/*/bin: {INSTALL_HINT}"
    )


# ----------------------------------------------------------------------------- embedded cluster


def _as_root() -> bool:
    return os.geteuid() == 0


def _pg_user() -> pwd.struct_passwd:
    try:
        return pwd.getpwnam(PG_OS_USER)
    except KeyError:
        raise DatabaseError(
            f"running as root, the embedded cluster must run as the {PG_OS_USER!r} OS user, "
            f"which does not exist: {INSTALL_HINT} (it creates that user)"
        ) from None


def _run_pg(argv: list[str], timeout: float = 120) -> subprocess.CompletedProcess[str]:
    """Run a PostgreSQL program, as the postgres OS user when we are root (initdb/postgres refuse root)."""
    if _as_root():
        _pg_user()
        runuser = shutil.which("runuser") or "/usr/sbin/runuser"
        argv = [runuser, "-u", PG_OS_USER, "--", *argv]
    try:
        return subprocess.run(argv, capture_output=True, text=True, timeout=timeout, cwd="/")
    except subprocess.TimeoutExpired:
        raise DatabaseError(f"{Path(argv[0]).name} did not finish in {timeout:.0f}s: {' '.join(argv)}") from None
    except OSError as e:
        raise DatabaseError(f"cannot run {argv[0]}: {e}") from None


def _check_traversable(path: Path, user: pwd.struct_passwd) -> None:
    for parent in reversed(path.resolve().parents):
        if not traversable_by(parent, user):
            raise DatabaseError(
                f"the embedded cluster runs as OS user {user.pw_name!r} (we are root), which cannot enter "
                f"{parent} (mode {stat.filemode(parent.stat().st_mode)}): put var/ somewhere it can reach "
                f"(GWC_VAR=/var/tmp/...), or chmod o+x {parent}"
            )


def _postmaster_pid(cfg: Config) -> int | None:
    try:
        first = (cfg.pg_dir / "postmaster.pid").read_text().split("\n", 1)[0]
        return int(first)
    except (OSError, ValueError):
        return None


def cluster_running(cfg: Config) -> bool:
    """Whether the embedded cluster's postmaster is alive (by its pid file; a stale file is ignored)."""
    pid = _postmaster_pid(cfg)
    if pid is None:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass
    with contextlib.suppress(OSError):
        comm = Path(f"/proc/{pid}/comm").read_text().strip()
        return comm in ("postgres", "postmaster")
    return True


@contextlib.contextmanager
def _cluster_lock(cfg: Config) -> Iterator[None]:
    """Serialise start/stop of one cluster between processes (two `gwc start` at once)."""
    secure_var(cfg)
    with os.fdopen(open_lock(cfg.run_dir / "pg.lock"), "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _conf_value(v: Any) -> str:
    if isinstance(v, bool):
        return "on" if v else "off"
    if isinstance(v, (int, float)):
        return str(v)
    return "'" + str(v).replace("'", "''") + "'"


def _write_settings(cfg: Config, owner: pwd.struct_passwd | None) -> None:
    settings = {**DEFAULT_SETTINGS, **cfg.raw.get("database", {}).get("settings", {})}
    host = cfg.database_host
    settings.update(
        listen_addresses=host.address if host else "", unix_socket_directories=str(socket_dir(cfg)), port=db_port(cfg)
    )
    lots = lot_access(cfg) if owner is None else None
    if lots is not None:  # its socket open to the lot user's group; who logs in as whom: write_hba
        settings.update(unix_socket_group=lots[0], unix_socket_permissions="0770")
    write_hba(cfg, host, owner, lots)
    if host is not None and uses_tls(cfg):
        make_certificate(cfg, host, owner)
        settings.update(ssl=True, ssl_cert_file="server.crt", ssl_key_file="server.key")
    lines = ["# Written by gwc.db at every start; edit etc/cell.toml [database.settings] instead."]
    lines += [f"{k} = {_conf_value(v)}" for k, v in settings.items()]
    conf = cfg.pg_dir / "gwc.conf"
    conf.write_text("\n".join(lines) + "\n")
    main = cfg.pg_dir / "postgresql.conf"
    if "include_if_exists = 'gwc.conf'" not in main.read_text():
        with main.open("a") as f:
            f.write("\ninclude_if_exists = 'gwc.conf'\n")
    if owner is not None:
        os.chown(conf, owner.pw_uid, owner.pw_gid)


def _log_tail(path: Path, lines: int = 15) -> str:
    try:
        return " | ".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return "(no server log)"


def _prepare_dirs(cfg: Config) -> pwd.struct_passwd | None:
    """Make var/pg and var/run usable by whoever runs the server; return that user when we are root."""
    secure_var(cfg)
    cfg.pg_dir.mkdir(parents=True, exist_ok=True)
    socket_dir(cfg).mkdir(mode=0o700, exist_ok=True)
    if len(str(socket_path(cfg))) >= SOCKET_MAX:
        raise DatabaseError(
            f"unix socket path {socket_path(cfg)} is longer than {SOCKET_MAX - 1} bytes: use a shorter var/ (GWC_VAR)"
        )
    if not _as_root():
        cfg.pg_dir.chmod(0o700)
        lots = hostuser.lot_group(cfg)
        if lots is not None:  # lot scripts of their own user reach the socket (its auth: write_hba)
            private_dir(socket_dir(cfg), lots)
        return None
    user = _pg_user()
    _check_traversable(cfg.pg_dir, user)
    _check_traversable(socket_dir(cfg), user)
    # var/ and var/run are root's, 0710 with postgres's group (private.secure_var): it passes through
    os.lchown(socket_dir(cfg), user.pw_uid, user.pw_gid)
    socket_dir(cfg).chmod(0o700)
    if not (cfg.pg_dir / "PG_VERSION").exists():
        for root, dirs, files in os.walk(cfg.pg_dir):
            for name in dirs + files:
                os.lchown(os.path.join(root, name), user.pw_uid, user.pw_gid)
    os.chown(cfg.pg_dir, user.pw_uid, user.pw_gid)
    cfg.pg_dir.chmod(0o700)
    return user


def _admin_conninfo(cfg: Config, dbname: str) -> str:
    return psycopg.conninfo.make_conninfo(host=str(socket_dir(cfg)), port=db_port(cfg), user=SUPERUSER, dbname=dbname)


def _ensure_database(cfg: Config, log: logging.Logger) -> None:
    with psycopg.connect(_admin_conninfo(cfg, "postgres"), autocommit=True) as conn:
        if conn.execute("select 1 from pg_database where datname = %s", (DB_NAME,)).fetchone():
            return
        try:
            conn.execute(sql.SQL("create database {}").format(sql.Identifier(DB_NAME)))
            log.info("created database %s", DB_NAME)
        except psycopg.errors.DuplicateDatabase:
            pass


def cluster_start(cfg: Config, log: logging.Logger | None = None) -> None:
    """Create (first time: initdb) and start the embedded cluster, and make sure database gwc exists.

    A no-op apart from that check when it already runs. Returns once it accepts connections.
    """
    log = log or _log
    with _cluster_lock(cfg):
        if not cluster_running(cfg):
            owner = _prepare_dirs(cfg)
            if not (cfg.pg_dir / "PG_VERSION").exists():
                log.info("initdb: creating the embedded cluster in %s", cfg.pg_dir)
                r = _run_pg(
                    [
                        str(find_pg_bin("initdb")),
                        "-D",
                        str(cfg.pg_dir),
                        "-U",
                        SUPERUSER,
                        "--auth=trust",
                        "--encoding=UTF8",
                        "--locale=C",
                    ]
                )
                if r.returncode != 0:
                    raise DatabaseError(f"initdb failed in {cfg.pg_dir}: {(r.stderr or r.stdout).strip()[-800:]}")
            _write_settings(cfg, owner)
            logfile = cfg.pg_dir / "server.log"
            r = _run_pg(
                [str(find_pg_bin("pg_ctl")), "start", "-w", "-t", "60", "-s", "-D", str(cfg.pg_dir), "-l", str(logfile)]
            )
            if r.returncode != 0 or not cluster_running(cfg):
                raise DatabaseError(
                    f"the embedded cluster in {cfg.pg_dir} did not start: "
                    f"{(r.stderr or r.stdout).strip()[-400:]} | server log: {_log_tail(logfile)}"
                )
            log.info("embedded cluster started (socket in %s)", socket_dir(cfg))
        _ensure_database(cfg, log)


def cluster_stop(cfg: Config, log: logging.Logger | None = None) -> None:
    """Stop the embedded cluster (fast shutdown: open transactions roll back). No-op if stopped."""
    log = log or _log
    with _cluster_lock(cfg):
        if not cluster_running(cfg):
            return
        r = _run_pg([str(find_pg_bin("pg_ctl")), "stop", "-w", "-t", "60", "-s", "-m", "fast", "-D", str(cfg.pg_dir)])
        if r.returncode != 0 and cluster_running(cfg):
            raise DatabaseError(
                f"the embedded cluster in {cfg.pg_dir} did not stop: "
                f"{(r.stderr or r.stdout).strip()[-400:]} | server log: "
                f"{_log_tail(cfg.pg_dir / 'server.log')}"
            )
        log.info("embedded cluster stopped")
