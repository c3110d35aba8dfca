"""Who the cell runs as on its host: the cell's user, and the lot scripts' user (docs/security.md).

Root is needed only to set up. A `gwc` command run as root becomes the cell's user (`[cell] user`,
default `gwc`, a system user bin/setup makes) before it touches var/ or starts anything: var/ is given
to that user once (an older var/ was root's, its cluster `postgres`'s), then the process sets its
groups, gid and uid. What must stay privileged is kept as capabilities, never as root:

* `gwc start` and `gwc agent` keep CAP_SETUID, CAP_SETGID (to start lot scripts as the lot user),
  CAP_KILL (to stop them) and CAP_SYS_NICE (the agent's niceness); `gwc start` hands them to the agent
  it starts through the ambient set, and the agent clears its ambient set at once, so that nothing it
  execs (a module, a lot script, the database) inherits any.
* `gwc stop` keeps CAP_KILL (lot scripts of another user, when no agent runs).
* every other command keeps nothing.

Lot scripts run as `[lots] user` (default `gwc-lot`) when the agent may switch to it: a user holding
the lot key alone. The cell's user is a member of the lot user's group, so that it can give the lot
user what it needs and nothing more: var/, var/run, var/run/pg, var/secrets and var/log passable
(0710, that group), `lot.key` readable (0640), each script's log made for it (0660), var/lots
writable with the sticky bit (1770: a script replaces its own traveller, never another user's file).

`[cell] user = ""` keeps a cell as whoever starts it (the tests' private cells); `[lots] user = ""`
runs lot scripts as the cell's user.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import grp
import os
import pwd
import shutil
import stat
import subprocess
import sys
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

from gwc.config import PROJECT_ROOT, Config
from gwc.errors import GwcError

CELL_USER = "gwc"
LOT_USER = "gwc-lot"
CELL_UID_ENV = "GWC_CELL_UID"  # what a lot script started as the lot user is told the cell's user is

# linux/capability.h, linux/prctl.h
CAP_CHOWN, CAP_KILL, CAP_SETGID, CAP_SETUID, CAP_SYS_NICE = 0, 5, 6, 7, 23
AGENT_CAPS = (CAP_SETUID, CAP_SETGID, CAP_KILL, CAP_SYS_NICE)
STOP_CAPS = (CAP_KILL,)
_PR_SET_KEEPCAPS = 8
_PR_CAP_AMBIENT, _AMBIENT_RAISE, _AMBIENT_CLEAR_ALL = 47, 2, 4
_CAP_V3 = 0x20080522


class HostUserError(GwcError):
    """The cell cannot become its user: the user is missing, or cannot reach what the cell needs."""

    exit_code = 2


@dataclass(frozen=True)
class LotUser:
    """Whom the agent starts lot scripts as: None for the agent's own user."""

    uid: int
    gid: int
    name: str


def cell_user_name(cfg: Config) -> str:
    name = cfg.raw.get("cell", {}).get("user", CELL_USER)
    if not isinstance(name, str):
        raise HostUserError(f"{cfg.path}: [cell] user = {name!r} is not a user name")
    return name


def lot_user_name(cfg: Config) -> str:
    """`[lots] user`; by default `gwc-lot`, or "" (the cell's user) in a cell that runs as whoever starts it."""
    name = cfg.raw.get("lots", {}).get("user", LOT_USER if cell_user_name(cfg) else "")
    if not isinstance(name, str):
        raise HostUserError(f"{cfg.path}: [lots] user = {name!r} is not a user name")
    return name


def _user(name: str) -> pwd.struct_passwd | None:
    try:
        return pwd.getpwnam(name)
    except KeyError:
        return None


# ----------------------------------------------------------------------------- capabilities


class _Header(ctypes.Structure):
    _fields_ = [("version", ctypes.c_uint32), ("pid", ctypes.c_int)]


class _Data(ctypes.Structure):
    _fields_ = [("effective", ctypes.c_uint32), ("permitted", ctypes.c_uint32), ("inheritable", ctypes.c_uint32)]


_libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)


def _prctl(*args: int) -> None:
    if _libc.prctl(*(ctypes.c_ulong(a) for a in args)) != 0:
        e = ctypes.get_errno()
        raise OSError(e, os.strerror(e))


def _mask(caps: Iterable[int]) -> int:
    m = 0
    for c in caps:
        m |= 1 << c
    return m


def set_caps(caps: Iterable[int]) -> None:
    """This process's effective, permitted and inheritable capabilities: exactly `caps` (all below 32)."""
    m = _mask(caps)
    data = (_Data * 2)(_Data(m, m, m), _Data(0, 0, 0))
    if _libc.capset(ctypes.byref(_Header(_CAP_V3, 0)), data) != 0:
        e = ctypes.get_errno()
        raise OSError(e, f"capset: {os.strerror(e)}")


def effective_caps() -> int:
    """The effective set as a bit mask (/proc/self/status CapEff)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("CapEff:"):
            return int(line.split()[1], 16)
    return 0


def has_caps(caps: Iterable[int]) -> bool:
    m = _mask(caps)
    return effective_caps() & m == m


def clear_ambient() -> None:
    """Nothing this process execs inherits a capability (the agent, at its start)."""
    with contextlib.suppress(OSError):
        _prctl(_PR_CAP_AMBIENT, _AMBIENT_CLEAR_ALL, 0, 0, 0)


@contextlib.contextmanager
def ambient(caps: Iterable[int]) -> Iterator[None]:
    """What this process execs meanwhile gets `caps` (those it holds): how `gwc start` hands the agent its."""
    raised = False
    for c in caps:
        if has_caps([c]):
            with contextlib.suppress(OSError):
                _prctl(_PR_CAP_AMBIENT, _AMBIENT_RAISE, c, 0, 0)
                raised = True
    try:
        yield
    finally:
        if raised:
            clear_ambient()


# ----------------------------------------------------------------------------- becoming the cell's user


def traversable_by(path: Path, user: pwd.struct_passwd) -> bool:
    """Whether `user` may search (x) directory `path`, by its mode bits."""
    st = path.stat()
    gids = {user.pw_gid} | {g.gr_gid for g in grp.getgrall() if user.pw_name in g.gr_mem}
    if st.st_uid == user.pw_uid:
        return bool(st.st_mode & stat.S_IXUSR)
    if st.st_gid in gids:
        return bool(st.st_mode & stat.S_IXGRP)
    return bool(st.st_mode & stat.S_IXOTH)


def _reachable(path: Path, user: pwd.struct_passwd, what: str) -> None:
    for parent in reversed([path, *path.parents] if path.is_dir() else list(path.parents)):
        if parent.exists() and not traversable_by(parent, user):
            raise HostUserError(
                f"the cell runs as OS user {user.pw_name!r}, which cannot enter {parent} "
                f"({stat.filemode(parent.stat().st_mode)}), on the way to {what} {path}: move it where that "
                f"user can reach it, or `chmod o+x {parent}`"
            )


def cannot_run_as(user: pwd.struct_passwd, cfg: Config) -> str | None:
    """Why `user` cannot run this cell (None if it can): a folder on the way to var/, the configuration,
    Python or the gwc package it may not enter (a checkout under root's 0700 home, say)."""
    try:
        _reachable(cfg.var.parent, user, "var/")
        _reachable(cfg.path.resolve(), user, "the configuration")
        _reachable(Path(sys.executable).resolve().parent, user, "Python")
        _reachable(Path(os.__file__).resolve().parent, user, "Python's library")
        _reachable(PROJECT_ROOT, user, "the gwc package")
    except HostUserError as e:
        return str(e)
    return None


def cell_user_reaches(cfg: Config, path: Path) -> bool:
    """Whether the cell's user (when it is another than the caller) may walk to `path`."""
    name = cell_user_name(cfg)
    user = _user(name) if name else None
    if user is None or user.pw_uid == os.geteuid():
        return True
    try:
        _reachable(path.resolve(), user, "the folder")
    except HostUserError:
        return False
    return True


_said: set[str] = set()


def _say_once(text: str) -> None:
    """A warning on standard error, once a process: the cell could not drop to its user and runs on as
    the one who started it (so that a checkout the cell's user cannot reach still runs, as the Quick
    start must; `gwc check` names it too)."""
    if text not in _said:
        _said.add(text)
        print(text, file=sys.stderr)


def give_var(var: Path, user: pwd.struct_passwd) -> None:
    """var/ and all in it the cell user's (once: an older var/ was root's, var/pg `postgres`'s)."""
    if not var.exists():
        var.mkdir(mode=0o700, parents=True)
    st = var.lstat()
    if stat.S_ISLNK(st.st_mode) or not stat.S_ISDIR(st.st_mode):
        raise HostUserError(f"{var} is not a folder (a link?): refused; remove it")
    pg = var / "pg"
    if st.st_uid == user.pw_uid and not (pg.exists() and pg.lstat().st_uid != user.pw_uid):
        return
    for root, dirs, files in os.walk(var):
        for name in dirs + files:
            os.lchown(os.path.join(root, name), user.pw_uid, user.pw_gid)
    os.lchown(var, user.pw_uid, user.pw_gid)


def become_cell_user(cfg: Config, keep: Iterable[int] = ()) -> None:
    """As root: become the cell's user, keeping only capabilities `keep` (see the module docstring).
    A no-op for anyone else, or when `[cell] user` is ""."""
    if os.geteuid() != 0:
        return
    name = cell_user_name(cfg)
    if not name or name == "root":
        return
    user = _user(name)
    if user is None:
        raise HostUserError(
            f"the cell's OS user {name!r} does not exist: run bin/setup as root (it makes it), "
            f"or `gwc host users`, or name another in [cell] user"
        )
    why = cannot_run_as(user, cfg)
    if why is not None:
        _say_once(f"gwc: {why}: the cell runs as {pwd.getpwuid(os.geteuid()).pw_name}, not {name} (docs/security.md)")
        return
    give_var(cfg.var, user)
    for key in (cfg.bus.key_file, cfg.bus.lot_key_file):  # outside var/ (a mounted secret): the cell's too
        if key and Path(key).exists() and cfg.var.resolve() not in Path(key).resolve().parents:
            os.chown(key, user.pw_uid, -1)
    caps = tuple(keep)
    groups = os.getgrouplist(name, user.pw_gid)
    if caps:
        _prctl(_PR_SET_KEEPCAPS, 1, 0, 0, 0)
    os.setgroups(groups)
    os.setresgid(user.pw_gid, user.pw_gid, user.pw_gid)
    os.setresuid(user.pw_uid, user.pw_uid, user.pw_uid)
    if caps:
        set_caps(caps)
        _prctl(_PR_SET_KEEPCAPS, 0, 0, 0, 0)
    os.environ.update(HOME=user.pw_dir, USER=name, LOGNAME=name)
    os.umask(0o027)


# ----------------------------------------------------------------------------- the lot scripts' user


def lot_user(cfg: Config) -> LotUser | None:
    """The user lot scripts run as, if they run as another user than the caller and the caller may
    start them so (root, or CAP_SETUID and CAP_SETGID); None: they run as the caller."""
    name = lot_user_name(cfg)
    user = _user(name) if name else None
    if user is None or user.pw_uid == os.geteuid():
        return None
    if os.geteuid() != 0 and not has_caps((CAP_SETUID, CAP_SETGID)):
        return None
    if cannot_run_as(user, cfg) is not None:
        return None  # (lot_user_wanted_but_unusable says why)
    return LotUser(user.pw_uid, user.pw_gid, name)


def lot_uid(cfg: Config) -> int | None:
    """The uid lot scripts of another user than the caller run as (whether or not it may start them)."""
    name = lot_user_name(cfg)
    user = _user(name) if name else None
    return None if user is None or user.pw_uid == os.geteuid() else user.pw_uid


def lot_user_wanted_but_unusable(cfg: Config) -> str | None:
    """Why lot scripts will run as the cell's user although `[lots] user` names another (None: they won't)."""
    name = lot_user_name(cfg)
    if not name or lot_user(cfg) is not None:
        return None
    user = _user(name)
    if user is None:
        return f"the lot user {name!r} does not exist (bin/setup as root makes it)"
    if user.pw_uid == os.geteuid():
        return None
    why = cannot_run_as(user, cfg)
    if why is not None:
        return why
    return "the agent may not switch users (started neither as root nor with CAP_SETUID and CAP_SETGID)"


def lot_group(cfg: Config) -> int | None:
    """The lot user's group, when the cell's user belongs to it (so may give files to it); else None."""
    name = lot_user_name(cfg)
    user = _user(name) if name else None
    if user is None or user.pw_uid == os.geteuid():
        return None
    return user.pw_gid if user.pw_gid in os.getgroups() or os.geteuid() == 0 else None


def share_with_lots(path: Path, gid: int, mode: int) -> None:
    """Give the lot user's group `mode` on a file or folder of the cell's (never through a link)."""
    st = os.lstat(path)
    if stat.S_ISLNK(st.st_mode) or st.st_uid != os.geteuid():
        return  # not the cell's: private.py refuses such things where it matters
    if st.st_gid != gid:
        os.chown(path, -1, gid, follow_symlinks=False)
    if stat.S_IMODE(st.st_mode) != mode:
        os.chmod(path, mode)


def make_lot_file(path: Path, gid: int) -> None:
    """A file a lot script writes (its log): made by the cell, 0660 with the lot user's group."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND | os.O_NOFOLLOW | os.O_CLOEXEC, 0o660)
    try:
        st = os.fstat(fd)
        if st.st_uid == os.geteuid():
            if st.st_gid != gid:
                os.fchown(fd, -1, gid)
            os.fchmod(fd, 0o660)
    finally:
        os.close(fd)


# ----------------------------------------------------------------------------- setup


def ensure_users(cell: str = CELL_USER, lot: str = LOT_USER) -> list[str]:
    """Make the cell's and the lot scripts' system users (root only; bin/setup): each with a group of
    its own, no home, no login shell; the cell's user a member of the lot user's group. What was made."""
    if os.geteuid() != 0:
        raise HostUserError("only root can make the cell's users")
    useradd = shutil.which("useradd") or "/usr/sbin/useradd"
    nologin = shutil.which("nologin") or "/usr/sbin/nologin"
    made = []
    for name in (cell, lot):
        if name and _user(name) is None:
            home = "/nonexistent"
            argv = [useradd, "--system", "--user-group", "--home-dir", home, "--no-create-home", "--shell", nologin]
            subprocess.run([*argv, name], check=True, capture_output=True, text=True)
            made.append(name)
    if cell and lot:
        lot_gid = pwd.getpwnam(lot).pw_gid
        if lot_gid not in os.getgrouplist(cell, pwd.getpwnam(cell).pw_gid):
            usermod = shutil.which("usermod") or "/usr/sbin/usermod"
            subprocess.run([usermod, "-a", "-G", lot, cell], check=True, capture_output=True, text=True)
            made.append(f"{cell} in group {lot}")
    return made
