"""What the cell keeps to itself on its host: var/ and its runtime folder, pid files, locks, and which
processes `gwc stop` may signal (docs/security.md, Local users).

A local user must be unable to make anything the cell later trusts. So var/ and var/run are the
cell user's own, open to nobody else (0700; 0710 with the lot user's group when lot scripts run as
a user of their own, gwc.hostuser, who may then pass through to what is made for them; 0710 with
the embedded cluster's group when root runs the cell itself, so that the `postgres` user can reach
its own folders and nothing more); a folder of
another owner, or a link where a folder should be, is refused, never used. Files the cell makes
there are made exclusively and never through a link (O_EXCL, O_NOFOLLOW); a pid file or lock that
another user owns or may write is refused. And before `gwc stop` signals a process a pid file names,
it checks that the process is the cell's: the cell's user's, started with this cell's var/ or
configuration in its environment.
"""

from __future__ import annotations

import contextlib
import json
import os
import pwd
import stat
from pathlib import Path
from typing import Any

from gwc import hostuser
from gwc.config import Config
from gwc.errors import GwcError
from gwc.hostuser import traversable_by as traversable_by  # (re-exported: gwc.db)

PG_OS_USER = "postgres"  # who runs initdb/postgres when we are root: Debian's package creates it
PID_MODE = 0o640
LOCK_MODE = 0o600


class NotPrivate(GwcError):
    """A file or folder the cell relies on belongs to someone else, or others may change it."""

    exit_code = 2


def private_dir(path: Path, group: int | None = None, mode: int | None = None) -> Path:
    """Make `path` (and its parents) a folder of the cell's own: 0700, or 0710 (or `mode`) for `group`.

    A folder of another owner, or a link, is refused (NotPrivate), never changed or followed."""
    if mode is None:
        mode = 0o710 if group is not None else 0o700
    try:
        path.mkdir(mode=mode, parents=True)
    except FileExistsError:
        pass
    st = os.lstat(path)
    if not stat.S_ISDIR(st.st_mode):
        raise NotPrivate(f"{path} is not a folder (a link or a file put there?): refused; remove it")
    if st.st_uid != os.geteuid():
        raise NotPrivate(
            f"{path} belongs to uid {st.st_uid}, not to the cell's user (uid {os.geteuid()}): refused; "
            "remove it, or give it to the cell's user"
        )
    if group is not None and st.st_gid != group:
        os.chown(path, -1, group)
    if stat.S_IMODE(st.st_mode) != mode:
        os.chmod(path, mode)
    return path


def secure_var(cfg: Config) -> None:
    """var/ and var/run, the cell's own (see the module docstring): at every start, so that a var/ of an
    older version (var/run was 1777) is closed too."""
    group = None
    if os.geteuid() == 0 and cfg.embedded:  # the cluster runs as `postgres`: it may pass through, no more
        with contextlib.suppress(KeyError):
            group = pwd.getpwnam(PG_OS_USER).pw_gid
    lots = hostuser.lot_group(cfg) if group is None else None
    private_dir(cfg.var, group if lots is None else lots)
    private_dir(cfg.run_dir, group if lots is None else lots)
    if lots is not None:
        share_with_lot_user(cfg, lots)


def share_with_lot_user(cfg: Config, gid: int) -> None:
    """What lot scripts of another user (gwc.hostuser) need of var/, and nothing more: to pass through
    var/secrets to lot.key, lot.database and database.crt (0640: gwc_lot's password and the database's
    certificate, for a host other than the database's) and var/log to their own logs (made for them); to write their
    travellers in var/lots (1770: sticky, so none replaces a file it does not own)."""
    for folder, mode in ((cfg.var / "secrets", 0o710), (cfg.log_dir, 0o710), (cfg.var / "lots", 0o1770)):
        private_dir(folder, gid, mode)
    lot_key = Path(cfg.bus.lot_key_file or cfg.var / "secrets" / "lot.key")
    if lot_key.exists():
        hostuser.share_with_lots(lot_key, gid, 0o640)
    # gwc_lot's password alone (gwc.db.lot_passwords_file), and the database's certificate it is checked with
    for name in ("lot.database", "database.crt"):
        if (cfg.var / "secrets" / name).exists():
            hostuser.share_with_lots(cfg.var / "secrets" / name, gid, 0o640)


def _owned(fd: int, path: Path) -> None:
    st = os.fstat(fd)
    if st.st_uid not in (os.geteuid(), 0) or st.st_mode & 0o022:
        raise NotPrivate(
            f"{path} is not the cell's (owner uid {st.st_uid}, mode {stat.S_IMODE(st.st_mode):04o}): refused"
        )


def write_new(path: Path, data: bytes, mode: int = PID_MODE) -> None:
    """Write `path` whole, replacing it: through a file made exclusively, never through a link."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.unlink(missing_ok=True)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, mode)
    try:
        os.write(fd, data)
    finally:
        os.close(fd)
    os.replace(tmp, path)  # replaces a link planted at `path`, never writes where it points


def read_own(path: Path) -> str:
    """A file of the cell's (its user's or root's, written by nobody else), never through a link:
    OSError if it is missing, NotPrivate if it is someone else's."""
    fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK)
    try:
        _owned(fd, path)
        with os.fdopen(os.dup(fd), "r") as f:
            return f.read(65536)
    finally:
        os.close(fd)


def open_lock(path: Path) -> int:
    """A lock file's descriptor (for flock): made 0600 if missing, never through a link; one someone
    else made or may write is refused (a user holding it would make the cell wait forever)."""
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, LOCK_MODE)
    try:
        _owned(fd, path)
    except NotPrivate:
        os.close(fd)
        raise
    return fd


def pid_info(path: Path) -> dict[str, Any] | None:
    """A pid file's content, if it is the cell's and well formed; NotPrivate if someone else's."""
    try:
        info = json.loads(read_own(path))
        int(info["pid"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return info if isinstance(info, dict) else None


def not_the_cells(cfg: Config, pid: int) -> str | None:
    """Why process `pid` is not one of this cell's (None if it is): another user's, or not started with
    this cell's var/ or configuration (GWC_VAR, GWC_CONFIG in its environment: spawn_process and the
    systemd unit set them; a lot script, a fork of the agent, has the agent's)."""
    if pid <= 1:
        return f"pid {pid} is never the cell's"
    try:
        uid = os.stat(f"/proc/{pid}").st_uid
        if uid == hostuser.lot_uid(cfg):  # a lot script: its environment is not ours to read
            return _a_lot_script_of(cfg, pid)
        environ = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
    except OSError as e:
        return f"pid {pid} cannot be looked at ({e.strerror})"
    if uid != os.geteuid():
        return f"pid {pid} belongs to uid {uid}, not to the cell's user (uid {os.geteuid()})"
    env = dict(item.decode(errors="replace").partition("=")[::2] for item in environ if b"=" in item)
    for name, ours in (("GWC_VAR", cfg.var), ("GWC_CONFIG", cfg.path)):
        if env.get(name) and Path(env[name]).resolve() == ours.resolve():
            return None
    return f"pid {pid} was not started for this cell ({cfg.var}): no GWC_VAR or GWC_CONFIG of it"


def _a_lot_script_of(cfg: Config, pid: int) -> str | None:
    """Why a process of the lot user is not one of this cell's lot scripts (None if it is): its command
    line (readable by all) must be `... -m gwc.lot.run --entity E --var <this cell's var/>`, or, forked by
    the lot user's launcher (gwc/lot/launcher.py), the launcher's `... -m gwc.lot.launcher --var <var/>`."""
    try:
        argv = [a.decode(errors="replace") for a in Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")]
    except OSError as e:
        return f"pid {pid} cannot be looked at ({e.strerror})"
    if (
        ("gwc.lot.run" in argv or "gwc.lot.launcher" in argv)  # exec'd, or forked by the lot user's launcher
        and "--var" in argv[:-1]
        and Path(argv[argv.index("--var") + 1]).resolve() == cfg.var.resolve()
    ):
        return None
    return f"pid {pid} is the lot user's but not a lot script of this cell ({cfg.var})"


def cell_owner() -> tuple[int, int]:
    """The cell's user and group: this process's, or, in a lot script the agent started as the lot
    user, the agent's (told in GWC_CELL_UID, "uid:gid")."""
    told = os.environ.get(hostuser.CELL_UID_ENV, "")
    uid, _, gid = told.partition(":")
    if uid.isdigit() and gid.isdigit():
        return int(uid), int(gid)
    return os.geteuid(), os.getegid()


def check_trusted_file(path: Path, what: str = "file") -> None:
    """Refuse (NotPrivate) a file the cell would run as code unless only the cell's user or root could
    have written it: it and every folder above it owned by one of them, and writable by nobody else (a
    sticky folder, /tmp, protects the entries of its other users, so it may be writable by all)."""
    me, my_group = cell_owner()
    path = Path(os.path.abspath(path))
    for p in (path, *path.parents):
        try:
            st = os.stat(p)
        except OSError as e:
            raise NotPrivate(f"{what} {path}: cannot look at {p}: {e.strerror}") from None
        writable_by_others = st.st_mode & 0o002 and not (st.st_mode & stat.S_ISVTX and p != path)
        writable_by_group = st.st_mode & 0o020 and st.st_gid not in (0, my_group)
        if st.st_uid not in (0, me) or writable_by_others or writable_by_group:
            raise NotPrivate(
                f"{what} {path}: {p} is {stat.filemode(st.st_mode)}, owner uid {st.st_uid}, group {st.st_gid}: "
                "another user could change it, and the cell would run what they wrote: refused. Give it to "
                "the cell's user or root, writable only by its owner"
            )
