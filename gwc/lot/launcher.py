"""The lot user's launcher: one process of the lot user's, its imports done, that forks this host's lot
scripts, so that a script run as the lot user does not pay a fresh interpreter (about 0.3 s of CPU a
script) as an exec'd one does (gwc.lot.run.exec_lot_script).

Why a process of its own: where lot scripts run as the cell's user the agent forks them itself
(fork_lot_script), but a fork of the agent would carry the module key into the lot user's process
(docs/security.md). The launcher is exec'd as the lot user, as a script is, holds nothing the lot
user may not, and what it forks is the lot user's as an exec'd script is: its uid and gid the lot
user's, no other group, no capability.

The agent and its launcher talk over a socketpair (LotLauncher is the agent's half, `serve` the
launcher's): the launcher says `R` once its imports are done; the agent sends `E <entity>` with the
script's output file (SCM_RIGHTS); the launcher forks twice, the middle process exiting at once, and
answers `P <pid>` (or `X <why>`). The agent is a child subreaper (PR_SET_CHILD_SUBREAPER), so the
script, orphaned by the middle process before the launcher answers, is the agent's child: the agent
waits for it, its exit status and CPU, as for any script it started, and it outlives a launcher that
dies. The launcher ends when its socket closes (its agent stopped or died). When it is not ready or
does not answer, the agent execs the script as before, and starts a new launcher.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import ctypes
import logging
import os
import select
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from gwc.cell import Proc, lot_proc, out_file, spawn_process, write_pid_file
from gwc.config import Config, load_config
from gwc.errors import ConfigError, GwcError
from gwc.hostuser import CELL_UID_ENV, LotUser
from gwc.log import open_out
from gwc.lot.run import PR_SET_NAME, Forked, exec_lot_script, fork_child, make_lot_log, open_files
from gwc.retry import Deadline

ANSWER_S = 2.0  # s the agent waits for the launcher's answer before it execs the script instead
CLOSE_S = 0.5  # s a launcher has to exit once its socket closed, before SIGKILL
MAX_UNREADY = 3  # launchers in a row that end before they are ready: then scripts are exec'd for good
SWEEP_S = 5.0  # s between the agent's reaps of orphans it fostered (a script's own children)
PR_SET_CHILD_SUBREAPER = 36  # prctl(2)
LAUNCHER_COMM = b"lot-launcher"  # its name in /proc/PID/comm
LAUNCHER = "launcher"  # its name: var/log/launcher.out takes what it prints before it could log


def launcher_wanted(cfg: Config) -> bool:
    """`[lots] launcher` (default true): scripts of the lot user forked by its launcher; false: each exec'd."""
    wanted = cfg.raw.get("lots", {}).get("launcher", True)
    if not isinstance(wanted, bool):
        raise ConfigError(f"{cfg.path}: [lots] launcher = {wanted!r} is not true or false")
    return wanted


class LauncherError(GwcError):
    """The launcher did not start a script (not ready, gone, or it said why)."""


# ----------------------------------------------------------------------------- the launcher's half


def serve(cfg: Config, sock: socket.socket) -> int:
    """Fork a lot script for each `E <entity>` until the socket closes; the process's exit code."""
    sock.sendall(b"R\n")
    while True:
        try:
            data, fds, _flags, _addr = socket.recv_fds(sock, 64, 1)
        except ConnectionError:
            return 0
        if not data:
            return 0  # the agent closed its end (stopped, or died): nothing more will come
        try:
            words = data.decode(errors="replace").split()
            if len(words) != 2 or words[0] != "E" or not words[1].isdigit() or len(fds) != 1:
                raise ValueError(f"not a request: {data[:40]!r}")
            reply = f"P {fork_script(cfg, int(words[1]), fds[0])}\n"
        except (ValueError, OSError) as e:
            reply = f"X {' '.join(str(e).split())}\n"
        finally:
            for fd in fds:
                os.close(fd)
        sock.sendall(reply.encode())


def fork_script(cfg: Config, entity_id: int, out: int) -> int:
    """Fork entity E's lot script through a middle process that exits at once: its pid, the script
    orphaned to the agent (a subreaper) by the time this returns."""
    inherited = open_files()  # the script sheds these: the socket, and `out` once it is its output
    r, w = os.pipe()
    for stream in (sys.stdout, sys.stderr):  # nothing of ours written twice, once by the children
        stream.flush()
    middle = os.fork()
    if middle == 0:
        try:
            os.close(r)
            pid = os.fork()
            if pid == 0:
                os.close(w)
                fork_child(cfg, entity_id, out, inherited)  # never returns
            os.write(w, str(pid).encode())
        finally:
            os._exit(0)
    os.close(w)
    try:
        got = os.read(r, 32)
    finally:
        os.close(r)
        os.waitpid(middle, 0)  # exited: the script's parent is now the nearest subreaper
    if not got.isdigit():
        raise OSError(f"entity {entity_id}: the script's fork failed")
    return int(got)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m gwc.lot.launcher", description=__doc__.split("\n\n")[0])
    parser.add_argument("--var", required=True, help="the cell's var/ (`gwc stop` knows the cell's scripts by it)")
    parser.add_argument("--socket", type=int, required=True, help="the descriptor of its end of the agent's socketpair")
    args = parser.parse_args(argv)
    try:
        cfg = load_config()
        if Path(args.var).resolve() != cfg.var.resolve():
            raise ConfigError(f"--var {args.var} is not this cell's var/ ({cfg.var})")
    except GwcError as e:
        print(f"gwc.lot.launcher: {e}", file=sys.stderr)
        return e.exit_code
    ctypes.CDLL(None).prctl(PR_SET_NAME, LAUNCHER_COMM, 0, 0, 0)  # `ps -e`, top; its scripts rename themselves
    with socket.socket(fileno=args.socket) as sock:
        return serve(cfg, sock)


# ----------------------------------------------------------------------------- the agent's half


class LotLauncher:
    """The agent's end of its launcher: `script(entity)` starts a lot script as the lot user, forked by
    the launcher when it is ready, else exec'd (and a new launcher started)."""

    def __init__(self, cfg: Config, user: LotUser, log: logging.Logger, known: Callable[[], set[int]]) -> None:
        self.cfg, self.user, self.log = cfg, user, log
        self.known = known  # the pids the agent waits for itself: never reaped by the sweep
        self.popen: subprocess.Popen[bytes] | None = None
        self.sock: socket.socket | None = None
        self.ready = False
        self.subreaper = False
        self.unready = 0  # launchers in a row that ended before they were ready

    def start(self) -> None:
        """Become a subreaper and start a launcher (its imports take a moment: scripts are exec'd until it
        says it is ready). Without the subreaper the agent could not wait for what it forks: no launcher."""
        if not launcher_wanted(self.cfg):  # (a bad value stops the agent's start, saying why)
            self.log.info("no lot launcher ([lots] launcher = false): lot scripts are exec'd")
            return
        if not self.subreaper:
            if ctypes.CDLL(None, use_errno=True).prctl(PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) != 0:
                self.log.warning("no lot launcher: prctl(PR_SET_CHILD_SUBREAPER) failed: scripts are exec'd")
                return
            self.subreaper = True
            asyncio.get_running_loop().call_later(SWEEP_S, self._sweep_now)
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        try:
            proc = Proc(
                LAUNCHER,
                command=(sys.executable, "-m", "gwc.lot.launcher", "--var", str(self.cfg.var.resolve()),
                         "--socket", str(theirs.fileno())),
            )  # fmt: skip
            env = {CELL_UID_ENV: f"{os.geteuid()}:{os.getegid()}"}
            self.popen = spawn_process(
                self.cfg, proc, env, pass_fds=(theirs.fileno(),), user=(self.user.uid, self.user.gid), record=False
            )
        except OSError as e:
            ours.close()
            self.log.warning("lot launcher not started (%s): scripts are exec'd", e)
            return
        finally:
            theirs.close()
        self.sock, self.ready = ours, False
        asyncio.get_running_loop().add_reader(ours.fileno(), self._heard)
        self.log.info("lot launcher started (pid %d, user %s)", self.popen.pid, self.user.name)

    def script(self, entity_id: int) -> Forked:
        """Start entity E's lot script as the lot user: forked by the launcher, or exec'd."""
        if self.sock is not None and self.ready:
            try:
                pid: int | None = self._ask(entity_id)
            except (LauncherError, OSError) as e:
                pid = self._end()  # the script, if the launcher forked it before it failed
                how = "exec'd" if pid is None else f"forked (pid {pid}) before it failed"
                self.log.warning("lot launcher: %s: entity %d %s; a new launcher started", e, entity_id, how)
                self.start()
            if pid is not None:
                base = lot_proc(entity_id)
                write_pid_file(self.cfg, base.name, pid, [*base.command, "--var", str(self.cfg.var.resolve())])
                return Forked(pid)
        elif self.sock is None and self.subreaper and self.unready < MAX_UNREADY:
            self.start()  # the last one died
        return exec_lot_script(self.cfg, entity_id, self.user)

    def _heard(self) -> None:
        """The launcher spoke unasked: `R` once its imports are done; the socket's end when it died."""
        if self.sock is None:
            return
        try:
            said = self.sock.recv(64)
        except OSError:
            said = b""
        if said == b"R\n" and not self.ready:
            self.ready, self.unready = True, 0
            self.log.info("lot launcher ready: lot scripts are forked from it")
            return
        self.unready += 0 if self.ready else 1
        self.log.warning("lot launcher %s: lot scripts are exec'd until a new one is ready", _ended(said))
        self.close()
        if self.unready >= MAX_UNREADY:
            self.log.error("lot launcher: %d in a row ended before they were ready: no more are started", self.unready)

    def _ask(self, entity_id: int) -> int:
        assert self.sock is not None
        make_lot_log(self.cfg, entity_id, self.user)
        out = open_out(out_file(self.cfg, lot_proc(entity_id).name))
        try:
            socket.send_fds(self.sock, [f"E {entity_id}\n".encode()], [out])
        finally:
            os.close(out)
        if not select.select([self.sock], [], [], ANSWER_S)[0]:
            raise LauncherError(f"no answer within {ANSWER_S:g}s")
        said = self.sock.recv(256).decode(errors="replace").split(maxsplit=1)
        if len(said) == 2 and said[0] == "P" and said[1].strip().isdigit():
            return int(said[1])
        raise LauncherError(said[1].strip() if len(said) == 2 and said[0] == "X" else _ended(" ".join(said).encode()))

    def _end(self) -> int | None:
        """End a launcher that failed a request: SIGKILL its process group (itself, a middle process, a
        script not yet in a session of its own). The request's script if it escaped into its own session
        first, and so is this agent's child now (its subreaper's), else None: never a second script."""
        group = self.popen.pid if self.popen is not None else None
        if group is not None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(group, signal.SIGKILL)
        self.close()
        if group is None:
            return None
        deadline = Deadline(CLOSE_S)
        while True:
            forks = _forks(self.cfg)
            if not any(f.pgrp == group and f.state != "Z" for f in forks) or deadline.expired:
                break  # the killed are dead: what escaped has been handed to this agent
            time.sleep(0.01)
        known = self.known()
        mine = os.getpid()
        escaped = [f.pid for f in forks if f.sid == f.pid and f.ppid == mine and f.state != "Z" and f.pid not in known]
        return escaped[0] if escaped else None

    def _sweep_now(self) -> None:
        for pid in self.sweep():
            self.log.info("reaped pid %d, an orphan of a lot script's (this agent is their subreaper)", pid)
        asyncio.get_running_loop().call_later(SWEEP_S, self._sweep_now)

    def sweep(self) -> list[int]:
        """Reap the orphans a subreaper fosters that no one waits for (a script's own children, or the
        launcher's); the pids reaped. A zombie the agent waits for itself ends the sweep: it is next."""
        reaped: list[int] = []
        launcher = self.popen.pid if self.popen is not None else None
        while True:
            try:
                info = os.waitid(os.P_ALL, 0, os.WEXITED | os.WNOHANG | os.WNOWAIT)
            except ChildProcessError:
                return reaped
            if info is None or info.si_pid in self.known() or info.si_pid == launcher:
                return reaped
            with contextlib.suppress(ChildProcessError):
                os.waitpid(info.si_pid, 0)
            reaped.append(info.si_pid)

    def close(self) -> None:
        """Close the socket (the launcher exits at that) and reap it; SIGKILL if it lingers."""
        if self.sock is not None:
            asyncio.get_running_loop().remove_reader(self.sock.fileno())
            self.sock.close()
            self.sock = None
        self.ready = False
        if self.popen is not None:
            try:
                self.popen.wait(CLOSE_S)  # it exits at the socket's end
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait()
            self.popen = None


@dataclass(frozen=True)
class Fork:
    """A process whose command line is the launcher's: the launcher, a middle process, or a script."""

    pid: int
    state: str
    ppid: int
    pgrp: int
    sid: int


def _forks(cfg: Config) -> list[Fork]:
    """The live processes whose command line is this cell's launcher's (/proc)."""
    found = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        with contextlib.suppress(OSError, ValueError, IndexError):
            argv = (d / "cmdline").read_bytes().split(b"\0")
            if b"gwc.lot.launcher" in argv and str(cfg.var.resolve()).encode() in argv:
                state, ppid, pgrp, sid = (d / "stat").read_text().rsplit(")", 1)[1].split()[:4]
                found.append(Fork(int(d.name), state, int(ppid), int(pgrp), int(sid)))
    return found


def _ended(said: bytes) -> str:
    return "ended" if not said else f"said {said[:40]!r}"


if __name__ == "__main__":
    sys.exit(main())
