"""The cell database: the embedded PostgreSQL cluster, connections with retry, one-transaction steps.

The thesis (3.2.2) asks every module to retry a failed database request and, when the failure is
fatal, to die cleanly; `connect` and `transaction` are those two rules, written once. The embedded
cluster is private to one cell: it lives in var/pg, listens on a unix socket in var/run and trusts
local connections. In a cell spread over several hosts it also listens on its host's address, where
each module's role logs in with its password (scram-sha-256) from the cell's subnet only, over TLS
when configured (docs/deploying.md).

Every module connects as the superuser of the cluster and then `SET ROLE gwc_<module>`, so the
table-ownership rule (thesis 5.1, GUIDE 4) is enforced by the server, not by convention.
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import grp
import logging
import os
import pwd
import re
import secrets
import shutil
import stat
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar
from urllib.parse import quote, urlsplit, urlunsplit

import psycopg
from psycopg import sql
from psycopg.conninfo import conninfo_attempts, conninfo_attempts_async, conninfo_to_dict

from gwc import hostuser
from gwc.budget import MAX_CONNECTIONS, plan
from gwc.config import Config, HostSpec, shipped
from gwc.errors import DatabaseError, DatabaseUnavailable
from gwc.private import PG_OS_USER, open_lock, private_dir, secure_var, traversable_by
from gwc.promotion import await_promotion, await_promotion_async, read_only_refusal
from gwc.retry import Backoff

T = TypeVar("T")

SQL_DIR = shipped("sql")
DB_NAME = "gwc"
SUPERUSER = "gwc"
LOT_ROLE = "lot"  # lot scripts' role: logs in as itself, with a connection limit (_limit_lot_connections)
SOCKET_MAX = 107  # sun_path limit on Linux, including the terminating NUL
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


def socket_dir(cfg: Config) -> Path:
    """The embedded cluster's socket and lock: a folder of its own, var/run stays the cell's alone."""
    return cfg.run_dir / "pg"


def _socket_path(cfg: Config) -> Path:
    return socket_dir(cfg) / f".s.PGSQL.{_port(cfg)}"


def _port(cfg: Config) -> int:
    return int(cfg.raw.get("database", {}).get("port", 5432))


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
        listen_addresses=host.address if host else "", unix_socket_directories=str(socket_dir(cfg)), port=_port(cfg)
    )
    lots = _lot_access(cfg) if owner is None else None
    if lots is not None:  # its socket open to the lot user's group; who logs in as whom: _write_hba
        settings.update(unix_socket_group=lots[0], unix_socket_permissions="0770")
    _write_hba(cfg, host, owner, lots)
    if host is not None and _tls(cfg):
        _make_certificate(cfg, host, owner)
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


# ----------------------------------------------------------------------------- across hosts


def _tls(cfg: Config) -> bool:
    return bool(cfg.raw.get("database", {}).get("tls", False))


def secrets_dir(cfg: Config) -> Path:
    """What every host of the cell needs and no one else may read: copied to each host by the operator."""
    return cfg.var / "secrets"


def _passwords_file(cfg: Config) -> Path:
    return secrets_dir(cfg) / "database"


def _ca_file(cfg: Config) -> Path:
    return secrets_dir(cfg) / "database.crt"


def role_passwords(cfg: Config) -> dict[str, str]:
    """Each module role's password ("role password" lines, mode 0600), made on the database host."""
    try:
        lines = _passwords_file(cfg).read_text().splitlines()
    except FileNotFoundError:
        raise DatabaseError(
            f"no database passwords at {_passwords_file(cfg)}: copy var/secrets/ from the database host "
            "(docs/deploying.md, Keys)"
        ) from None
    return dict(line.split(" ", 1) for line in lines if " " in line)


def _write_secret(path: Path, text: str) -> None:
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)


def _set_role_passwords(cur: psycopg.Cursor[Any], cfg: Config) -> None:
    """Let every module role log in from other hosts, each with its own password (made once, kept)."""
    roles = [r for (r,) in cur.execute("select rolname from pg_roles where rolname like 'gwc\\_%' order by 1")]
    try:
        known = role_passwords(cfg)
    except DatabaseError:
        known = {}
    passwords = {r: known.get(r) or secrets.token_urlsafe(24) for r in roles}
    for role, password in passwords.items():
        cur.execute(sql.SQL("alter role {} login password {}").format(sql.Identifier(role), sql.Literal(password)))
    if passwords != known:
        _write_secret(_passwords_file(cfg), "".join(f"{r} {p}\n" for r, p in passwords.items()))
    lot_role = f"gwc_{LOT_ROLE}"
    if lot_role in passwords and _lot_password(cfg) != passwords[lot_role]:
        _write_secret(lot_passwords_file(cfg), f"{lot_role} {passwords[lot_role]}\n")


def lot_passwords_file(cfg: Config) -> Path:
    """The lot scripts' own role's password alone (var/secrets/lot.database): shared with the lot user's
    group as lot.key is (gwc.private), so that a lot script on a host other than the database's can log
    in as gwc_lot (reads, and its own traveller) without reading the other roles' passwords."""
    return secrets_dir(cfg) / "lot.database"


def _lot_password(cfg: Config) -> str | None:
    with contextlib.suppress(OSError, ValueError):
        for line in lot_passwords_file(cfg).read_text().splitlines():
            role, _, password = line.partition(" ")
            if role == f"gwc_{LOT_ROLE}" and password:
                return password
    return None


def _lot_access(cfg: Config) -> tuple[str, str] | None:
    """(group, user) of the lot scripts' OS user when they run as one (gwc.hostuser) and so must reach
    the socket; None when only the cell's user does."""
    gid = hostuser.lot_group(cfg)
    if gid is None:
        return None
    return grp.getgrgid(gid).gr_name, hostuser.lot_user_name(cfg)


def _write_hba(
    cfg: Config, host: HostSpec | None, owner: pwd.struct_passwd | None, lots: tuple[str, str] | None = None
) -> None:
    """Local connections: trusted while only the cell's user can reach the socket; once the lot user
    can, by the kernel's word on who connects (peer): the cell's user and root as the cell's superuser
    or the lots' role, the lot user as the lots' role alone. From the network only the cell's subnet,
    each role by password."""
    lines = ["# Written by gwc.db at every start; edit etc/cell.toml [database] allow/tls instead."]
    lines.append("local all all peer map=cell" if lots else "local all all trust")
    if host is not None:
        allow = cfg.raw.get("database", {}).get("allow") or f"{host.address.rsplit('.', 1)[0]}.0/24"
        lines.append(f"{'hostssl' if _tls(cfg) else 'host'} {DB_NAME} all {allow} scram-sha-256")
    hba = cfg.pg_dir / "pg_hba.conf"
    hba.write_text("\n".join(lines) + "\n")
    if lots is not None:
        me = pwd.getpwuid(os.geteuid()).pw_name
        pairs = [(who, role) for who in dict.fromkeys((me, "root")) for role in (SUPERUSER, f"gwc_{LOT_ROLE}")]
        pairs.append((lots[1], f"gwc_{LOT_ROLE}"))
        (cfg.pg_dir / "pg_ident.conf").write_text("".join(f"cell {who} {role}\n" for who, role in pairs))
    if owner is not None:
        os.chown(hba, owner.pw_uid, owner.pw_gid)


def _make_certificate(cfg: Config, host: HostSpec, owner: pwd.struct_passwd | None) -> None:
    """A self-signed certificate for the host's address, made once; its public half goes to
    var/secrets/, so the other hosts can verify the server they talk to (sslmode=verify-ca)."""
    crt, key = cfg.pg_dir / "server.crt", cfg.pg_dir / "server.key"
    if not crt.exists():
        r = subprocess.run(
            ["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "3650", "-subj",
             f"/CN={host.address}", "-addext", f"subjectAltName=IP:{host.address}",
             "-keyout", str(key), "-out", str(crt)],
            capture_output=True, text=True,
        )  # fmt: skip
        if r.returncode != 0:
            raise DatabaseError(f"cannot make the database's TLS certificate: {r.stderr.strip()[-300:]}")
        key.chmod(0o600)
        if owner is not None:
            for f in (crt, key):
                os.chown(f, owner.pw_uid, owner.pw_gid)
    _write_secret(_ca_file(cfg), crt.read_text())


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
    if len(str(_socket_path(cfg))) >= SOCKET_MAX:
        raise DatabaseError(
            f"unix socket path {_socket_path(cfg)} is longer than {SOCKET_MAX - 1} bytes: use a shorter var/ (GWC_VAR)"
        )
    if not _as_root():
        cfg.pg_dir.chmod(0o700)
        lots = hostuser.lot_group(cfg)
        if lots is not None:  # lot scripts of their own user reach the socket (its auth: _write_hba)
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
    return psycopg.conninfo.make_conninfo(host=str(socket_dir(cfg)), port=_port(cfg), user=SUPERUSER, dbname=dbname)


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


# ----------------------------------------------------------------------------- connections


def database_url(cfg: Config, role: str | None = None) -> str:
    """The URL the cell uses: GWC_DATABASE_URL / [database] url, else the embedded cluster's socket, or
    from another host of the cell its address, as the module's role (gwc_hi for the operator's tools)."""
    if cfg.database_url:
        return cfg.database_url
    port = _port(cfg)
    host = cfg.database_host
    if (host is not None and host.name != cfg.host) or (role == LOT_ROLE and cfg.embedded):
        # From another host every role logs in as itself; on the database's host lot scripts do too,
        # so that their role's connection limit holds them to their share (_limit_lot_connections).
        user = f"gwc_{role or 'hi'}"
        if host is None or host.name == cfg.host:
            return f"postgresql://{user}@/{DB_NAME}?host={quote(str(socket_dir(cfg)), safe='')}" + (
                f"&port={port}" if port != 5432 else ""
            )
        password = _lot_password(cfg) if role == LOT_ROLE else None
        password = password or role_passwords(cfg).get(user)
        if password is None:
            raise DatabaseError(f"no password for {user} in {_passwords_file(cfg)}: copy it from the database host")
        tls = f"?sslmode=verify-ca&sslrootcert={quote(str(_ca_file(cfg)), safe='')}" if _tls(cfg) else ""
        return f"postgresql://{user}:{quote(password, safe='')}@{host.address}:{port}/{DB_NAME}{tls}"
    return f"postgresql://{SUPERUSER}@/{DB_NAME}?host={quote(str(socket_dir(cfg)), safe='')}" + (
        f"&port={port}" if port != 5432 else ""
    )


def _redact(url: str) -> str:
    """The URL without its password, for messages and logs."""
    with contextlib.suppress(ValueError):
        parts = urlsplit(url)
        if parts.password:
            netloc = parts.netloc.replace(f":{parts.password}@", ":***@")
            return urlunsplit(parts._replace(netloc=netloc))
    return re.sub(r"password=\S+", "password=***", url)


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split()) or type(e).__name__


_ROLE = re.compile(r"^[a-z][a-z0-9_]*$")
# A TCP connection (from another host) is watched by the kernel, not by queries: probed after 3 s of
# silence, dead after 3 probes unanswered. Data unacknowledged for 8 s ends it: a query on a cut link
# fails instead of holding its module for TCP's ~15 min of retries. The socket then turns readable, as
# a resting module's watch sees without a round trip (gwc/module.py). libpq ignores it on a Unix socket.
_KEEPALIVE = {"keepalives": 1, "keepalives_idle": 3, "keepalives_interval": 1, "keepalives_count": 3}
# Data unacknowledged this long ends the connection (ms). The peer's kernel acknowledges, not its
# PostgreSQL, so a loaded server does not trip it; a dead host (a database failover's old primary)
# does, and a module's query on it fails after 4 s instead of holding its step (docs/reliability.md).
TCP_WATCH: dict[str, Any] = {**_KEEPALIVE, "tcp_user_timeout": 4000}
CONNECT_TIMEOUT_S = 5  # a connect's bound, unless the URL says (`connect_timeout`)
SLOW_MEMBER_S = 0.25  # s: how long a multi-host connect waits for a silent member once the others refused


def connect(
    cfg: Config,
    role: str | None = None,
    log: logging.Logger | None = None,
    attempts: int = 5,
    promotion_wait: float = 0.0,
) -> psycopg.Connection[Any]:
    """Connect (autocommit off) as role gwc_<role>, retrying with backoff (thesis 3.2.2).

    Raises DatabaseUnavailable after the last try; DatabaseError at once if the role is unknown
    (that is not transient: the schema has not been applied). `promotion_wait` (s): how long a try
    may watch the standbys of a database failing over for the one promoted (PROMOTION_POLL_S), for a
    caller in a thread of its own that would try again anyway.
    """
    log = log or _log
    if role is not None and not _ROLE.match(role):
        raise DatabaseError(f"bad database role name {role!r}")
    url = database_url(cfg, role)
    error: Exception | None = None
    backoff = Backoff(0.1, 2.0, attempts=attempts, jitter=0.2)
    while True:
        attempt = backoff.tries + 1
        try:
            conn = _connect_any(url, f"gwc_{role}" if role else "gwc", promotion_wait)
        except psycopg.OperationalError as e:
            error = e
            pause = backoff.next()
            if pause is None:
                break  # the caller hears of it (DatabaseUnavailable)
            log.warning(
                "database connect failed (try %d of %d) to %s: %s", attempt, attempts, _redact(url), _one_line(e)
            )
            time.sleep(pause)
            continue
        if role is not None:
            try:
                conn.execute(sql.SQL("set role {}").format(sql.Identifier(f"gwc_{role}")))
                conn.commit()
            except psycopg.OperationalError as e:  # the server went away meanwhile
                conn.close()
                raise DatabaseUnavailable(f"cell database connection lost at once: {_one_line(e)}") from e
            except psycopg.Error as e:
                conn.close()
                raise DatabaseError(
                    f"cannot act as database role gwc_{role}: {_one_line(e)} "
                    f"(has the schema been applied? try `gwc db init`)"
                ) from e
        return conn
    raise DatabaseUnavailable(
        f"cannot connect to the cell database at {_redact(url)} after {attempts} tries "
        f"({_one_line(error) if error else 'no attempt'}): is the cell database running? try `gwc db start`"
    ) from error


def _connect_any(url: str, application_name: str, promotion_wait: float = 0.0) -> psycopg.Connection[Any]:
    """psycopg.connect(url), but a multi-host URL's members are tried all at once, not in turn.

    libpq (and psycopg) try the members of `host=a,b,c` one after the other, each for up to
    `connect_timeout`: after a database failover whose old primary's host is dead (its packets lost,
    not refused) every connect paid that member's whole timeout before it tried the new primary. Here
    each member is tried in a thread of its own with the URL's options (target_session_attrs among
    them); the first that accepts wins and the others are closed. Once a member has refused and only
    silent ones are left, they are waited for at most SLOW_MEMBER_S: the caller's backoff tries again
    soon rather than waiting out a dead host's timeout. With `promotion_wait`, a member that refused
    for being a standby is watched until it is promoted (see PROMOTION_POLL_S), for that long."""
    given = conninfo_to_dict(url)
    options: dict[str, Any] = {"application_name": application_name, **TCP_WATCH}
    if "connect_timeout" not in given:
        options["connect_timeout"] = CONNECT_TIMEOUT_S
    attempts = conninfo_attempts({**given, **options})
    if len(attempts) < 2 and promotion_wait <= 0:
        return psycopg.connect(url, autocommit=False, **options)
    return _race(attempts, promotion_wait)


async def connect_async(cfg: Config, role: str, promotion_wait: float = 0.0) -> psycopg.AsyncConnection[Any]:
    """One try at a connection as role gwc_<role> (autocommit), for an event loop that must run no
    thread: the host agent, which forks lot scripts. Every member of a multi-host URL at once, as
    _connect_any (and, with `promotion_wait`, its standbys watched for the one promoted);
    DatabaseUnavailable when none accepts, DatabaseError when the role cannot be taken."""
    if not _ROLE.match(role):
        raise DatabaseError(f"bad database role name {role!r}")
    url = database_url(cfg, role)
    given = conninfo_to_dict(url)
    options: dict[str, Any] = {"application_name": f"gwc_{role}", **TCP_WATCH}
    if "connect_timeout" not in given:
        options["connect_timeout"] = CONNECT_TIMEOUT_S
    attempts: list[dict[str, Any]] = await conninfo_attempts_async({**given, **options})
    loop = asyncio.get_running_loop()
    watch_until = loop.time() + promotion_wait
    watching = 0

    async def one(params: dict[str, Any]) -> psycopg.AsyncConnection[Any]:
        nonlocal watching
        try:
            return await psycopg.AsyncConnection.connect(**params, autocommit=True)
        except psycopg.Error as e:
            if promotion_wait <= 0 or not read_only_refusal(e):
                raise
            watching += 1
            try:
                promoted = await await_promotion_async(params, watch_until)
            finally:
                watching -= 1
            if promoted is None:
                raise
            return promoted

    pending = {asyncio.ensure_future(one(a)) for a in attempts}
    deadline = loop.time() + max(float(a.get("connect_timeout") or CONNECT_TIMEOUT_S) for a in attempts)
    errors: list[str] = []
    refused_at: float | None = None
    conn: psycopg.AsyncConnection[Any] | None = None
    try:
        while pending and conn is None:
            until = deadline if refused_at is None else min(deadline, refused_at + SLOW_MEMBER_S)
            if watching:
                until = max(until, watch_until)
            if until <= loop.time():
                break
            left = until - loop.time()
            done, pending = await asyncio.wait(pending, timeout=left, return_when=asyncio.FIRST_COMPLETED)
            for task in done:
                if (error := task.exception()) is not None:
                    errors.append(_one_line(error))
                    refused_at = refused_at or loop.time()
                elif conn is None:
                    conn = task.result()
                else:
                    await task.result().close()
    finally:
        for task in pending:
            task.cancel()
    if conn is None:
        why = "; ".join(errors) or "no answer"
        raise DatabaseUnavailable(f"cannot connect to the cell database at {_redact(url)}: {why}")
    try:
        await conn.execute(sql.SQL("set role {}").format(sql.Identifier(f"gwc_{role}")))
    except psycopg.OperationalError as e:
        await conn.close()
        raise DatabaseUnavailable(f"cell database connection lost at once: {_one_line(e)}") from e
    except psycopg.Error as e:
        await conn.close()
        raise DatabaseError(f"cannot act as database role gwc_{role}: {_one_line(e)} (try `gwc db init`)") from e
    return conn


def _race(attempts: list[dict[str, Any]], promotion_wait: float = 0.0) -> psycopg.Connection[Any]:
    """The first of the members' connections to succeed (see _connect_any); the others are closed."""
    done = threading.Condition()
    errors: list[str] = []
    won: list[psycopg.Connection[Any] | None] = []  # [conn] once one won, [None] once given up
    watching = [0]  # members being watched for a promotion
    start = time.monotonic()
    watch_until = start + promotion_wait

    def one(params: dict[str, Any]) -> None:
        try:
            conn = psycopg.connect(**params, autocommit=False)
        except psycopg.Error as e:
            promoted = None
            if promotion_wait > 0 and read_only_refusal(e):
                with done:
                    watching[0] += 1
                    done.notify_all()
                try:
                    promoted = await_promotion(params, watch_until, lambda: bool(won))
                finally:
                    with done:
                        watching[0] -= 1
            if promoted is None:
                with done:
                    errors.append(f"{params.get('host')}: {_one_line(e)}")
                    done.notify_all()
                return
            conn = promoted
        with done:
            if not won:
                won.append(conn)
                done.notify_all()
                return
        conn.close()  # another member won, or the caller gave up

    for params in attempts:
        threading.Thread(target=one, args=(params,), name="gwc-db-connect", daemon=True).start()
    deadline = start + max(float(p.get("connect_timeout") or CONNECT_TIMEOUT_S) for p in attempts)
    refused_at: float | None = None
    with done:
        while not won and len(errors) < len(attempts):
            now = time.monotonic()
            if errors and refused_at is None:
                refused_at = now
            until = deadline if refused_at is None else min(deadline, refused_at + SLOW_MEMBER_S)
            if watching[0]:
                until = max(until, watch_until)
            if now >= until:
                break
            done.wait(until - now)
        if won:
            conn = won[0]
            assert conn is not None
            return conn
        won.append(None)
        silent = len(attempts) - len(errors)
        raise psycopg.OperationalError(
            "no member accepted: " + "; ".join(errors + ([f"{silent} silent"] if silent else []))
        )


def probe(cfg: Config) -> str | None:
    """Whether the cell database answers now: None if it does, else why not (for `gwc status`)."""
    try:
        with psycopg.connect(database_url(cfg), connect_timeout=3) as conn:
            conn.execute("select 1")
    except psycopg.Error as e:
        return _one_line(e)
    return None


ConnectionSource = psycopg.Connection[Any] | Callable[[], psycopg.Connection[Any]]


class Statement:
    """A database step that is one SQL statement: fetch "one" (a row or None), "all" (the rows) or None.

    `transaction` runs it alone, in autocommit: PostgreSQL makes a single statement atomic by itself,
    so the step needs no BEGIN and no COMMIT, each a round trip of its own (a one-row read takes about
    a third of the time, a one-row update two thirds, and the client's CPU halves: docs/performance.md).
    Made from one SQL text, it cannot grow a second statement that would then run outside a transaction.
    The connection is left in the mode it was in.
    """

    __slots__ = ("fetch", "into", "params", "sql")

    def __init__(
        self, sql: str, params: Any = (), fetch: str | None = "one", into: Callable[[Any], Any] | None = None
    ) -> None:
        if fetch not in ("one", "all", None):
            raise ValueError(f"fetch must be 'one', 'all' or None, not {fetch!r}")
        self.sql, self.params, self.fetch = sql, params, fetch
        self.into = into  # what a store makes of the fetched row(s): a dataclass (or a refusal raised)

    def __call__(self, cur: psycopg.Cursor[Any]) -> Any:
        cur.execute(self.sql, self.params)
        if self.fetch == "one":
            got = cur.fetchone()
        else:
            got = cur.fetchall() if self.fetch == "all" else None
        return got if self.into is None else self.into(got)


def _autocommit(conn: psycopg.Connection[Any], on: bool) -> bool:
    """Switch autocommit where psycopg allows it (an open connection outside a transaction); True if done."""
    if conn.closed or conn.info.transaction_status != psycopg.pq.TransactionStatus.IDLE:
        return False
    conn.autocommit = on
    return True


def transaction(
    conn: ConnectionSource,
    fn: Callable[[psycopg.Cursor[Any]], T],
    *,
    attempts: int = 3,
    log: logging.Logger | None = None,
) -> T:
    """Run fn(cursor) as one transaction and commit; retry the whole step on transient failures.

    `conn` is a connection or, better, a function returning one (like Module.db): a broken
    connection is closed and the function is called again for a fresh one. Anything left
    uncommitted on the connection beforehand is rolled back first. Transient failures
    (OperationalError: serialization failure, deadlock, lost connection, admin shutdown) are
    retried; after the last try, or at once for any other database error (constraint
    violation, bad SQL), DatabaseError is raised with the psycopg error as __cause__
    (DatabaseUnavailable when the connection was lost, or could not be made again). An
    exception of fn's own that is not a database error rolls back and propagates unchanged.

    A `Statement` runs alone, without BEGIN and COMMIT (see there).

    fn may run more than once: it must not have side effects outside the database. A commit
    lost with its connection may in fact have happened, so a step should be idempotent
    (ON CONFLICT, "where not exists") when it can be retried after a lost connection.
    """
    log = log or _log
    attempts = max(1, attempts)
    backoff = Backoff(0.05, 1.0, attempts=attempts, jitter=0.5)
    while True:
        attempt = backoff.tries + 1
        c = conn() if callable(conn) else conn
        try:
            if c.info.transaction_status != psycopg.pq.TransactionStatus.IDLE:
                c.rollback()
            was = c.autocommit  # a connection kept in autocommit (a lot script's) is left so
            alone = isinstance(fn, Statement) and (was or _autocommit(c, True))
            try:
                with c.cursor() as cur:
                    result = fn(cur)
            finally:
                if alone and not was:
                    _autocommit(c, False)
            if not alone:
                c.commit()
            return result
        except psycopg.OperationalError as e:
            _safe_rollback(c)
            broken = c.broken or c.closed
            if broken:
                c.close()
            pause = None if broken and not callable(conn) else backoff.next()
            log.warning(
                "database transaction failed (try %d of %d)%s: %s",
                attempt,
                attempts,
                ", connection lost" if broken else "",
                _one_line(e),
            )
            if pause is None:
                # A step that lost its connection is not refused: the database is away (ask again later).
                error = DatabaseUnavailable if broken else DatabaseError
                raise error(
                    f"database step failed after {attempt} tries: {_one_line(e)}"
                    + (" (connection lost)" if broken else "")
                ) from e
            time.sleep(pause)
        except psycopg.Error as e:
            _safe_rollback(c)
            raise DatabaseError(f"database step refused: {_one_line(e)}") from e
        except BaseException:
            _safe_rollback(c)
            raise


def _safe_rollback(conn: psycopg.Connection[Any]) -> None:
    with contextlib.suppress(psycopg.Error):
        if not conn.closed:
            conn.rollback()


# ----------------------------------------------------------------------------- schema


def sql_files() -> list[Path]:
    return sorted(SQL_DIR.glob("*.sql"))


def init_schema(cfg: Config, log: logging.Logger | None = None) -> None:
    """Apply sql/*.sql in name order (all idempotent), then register the machines of cell.toml.

    One transaction under an advisory lock, so two processes initialising at once take turns and a
    failure leaves the database as it was. Machines in cell.toml that the seed does not know get a
    me_config row, a 'Shutdown' machine_status row and, by kind, the seed's recipes.
    """
    log = log or _log
    files = sql_files()
    if not files:
        raise DatabaseError(f"no schema files in {SQL_DIR}: the checkout is incomplete")
    with connect(cfg, log=log) as conn:
        try:
            with conn.transaction(), conn.cursor() as cur:
                cur.execute("select pg_advisory_xact_lock(hashtext('gwc.init_schema'))")
                for path in files:
                    log.debug("applying %s", path.name)
                    try:
                        cur.execute(path.read_text())
                    except psycopg.Error as e:
                        raise DatabaseError(f"{path.name}: {_one_line(e)}") from e
                _register_machines(cur, cfg)
                if cfg.database_host is not None:
                    _set_role_passwords(cur, cfg)
                if cfg.embedded:
                    _limit_lot_connections(cur, cfg, log)
        except psycopg.Error as e:
            raise DatabaseError(f"applying the schema failed: {_one_line(e)}") from e
    log.info("schema applied (%s)", ", ".join(p.name for p in files))


def _limit_lot_connections(cur: psycopg.Cursor[Any], cfg: Config, log: logging.Logger) -> None:
    """Lot scripts log in as gwc_lot, whose connection limit is their share of the budget
    (gwc/budget.py): however many scripts run, on however many hosts, the modules and the operator
    keep theirs. The cell's own cluster only: a plant's server is its DBA's to size (docs/operating.md)."""
    budget = plan(cfg)
    cur.execute(sql.SQL("alter role gwc_lot login connection limit {}").format(sql.Literal(budget.lots)))
    log.info("database connections: %s", budget.describe())


# What a machine of each kind can do out of the box, as the seed gives the NJIT cell's machines.
KIND_RECIPES = {
    "cmm": [("alum_chess_set", "alum_chess")],
    "dummy": [("mill_pawn", "mill_chess"), ("dummy_recipe", "dummy_op"), ("dummy_recipe", "measure")],
}


def _register_machines(cur: psycopg.Cursor[Any], cfg: Config) -> None:
    for m in cfg.machines:
        cur.execute(
            "insert into me_config (machine_id, kind, liveness_s) values (%s, %s, %s) "
            "on conflict (machine_id) do update set kind = excluded.kind, liveness_s = excluded.liveness_s",
            (m.id, m.kind, m.liveness),
        )
        cur.execute(
            "insert into machine_status (machine_id, status) values (%s, 'Shutdown') on conflict do nothing", (m.id,)
        )
        for recipe_id, op_type in KIND_RECIPES.get(m.kind, []):
            cur.execute(
                "insert into op_machine_recipe (machine_id, recipe_id, op_type) "
                "select %s, %s, %s where exists (select 1 from recipes where recipe_id = %s) "
                "and exists (select 1 from op_types where op_type = %s) on conflict do nothing",
                (m.id, recipe_id, op_type, recipe_id, op_type),
            )


def get_new_max_value(cur_or_conn: psycopg.Cursor[Any] | psycopg.Connection[Any], type: str) -> int:
    """The next id of a kind (MACH_R_KEY, MACH_R_ID, ENTITY_ID, LOT_ID, WORK_ORDER, ALARM_NO).

    Strictly increasing per type and transactional: the counter row stays locked until the caller
    commits, so call it late in short transactions.
    """
    row = cur_or_conn.execute("select get_new_max_value(%s)", (type,)).fetchone()
    assert row is not None
    return int(row[0])
