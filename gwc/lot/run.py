"""`python -m gwc.lot.run --entity E`: the process of one operation entity (thesis 6.1).

The Human Interface has one of these started for every entity of an order (the thesis's HI used
fork/exec): by the host's agent, which forks it from itself (`fork_lot_script`: the agent has
imported what a lot script needs, so the new process does not spend 0.3 s of CPU importing it
again), or, where no agent runs, as a detached `python -m gwc.lot.run`. It finds the entity's lot
script through LOTS / PRODUCTS -> LOT_SCRIPTS.path, loads it, and calls its `main(entity)` inside
an OperationEntity, so whatever goes wrong in the script (an exception, a timeout, SIGTERM from
`gwc stop`) ends with the entity's requests cancelled, its machines unreserved and the entity
marked failed with the reason. Exit code 0 when the script finished its lot, non-zero otherwise.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import gc
import importlib.util
import json
import os
import signal
import subprocess
import sys
import traceback
from pathlib import Path
from types import FrameType, ModuleType
from typing import NoReturn

from gwc.cell import Proc, lot_proc, out_file, pid_file, process_env, spawn_process, write_pid_file
from gwc.config import PROJECT_ROOT, Config, load_config
from gwc.errors import ConfigError, GwcError
from gwc.hostuser import CELL_UID_ENV, LotUser, make_lot_file
from gwc.log import MAX_LOG_BYTES, CappedFileHandler, cap_output, log_file_name, open_log, open_out
from gwc.lot.entity import OperationEntity
from gwc.lot.errors import LotError, ScriptStopped
from gwc.lot.spawn import spawn_lot_script as spawn_lot_script  # (re-exported: gwc.client.orders, gwc.soak, gwc.bench)
from gwc.lot.spawn import spawn_lot_scripts as spawn_lot_scripts
from gwc.private import NotPrivate, check_trusted_file, secure_var

SWITCH_INTERVAL = 0.0005  # seconds
PR_SET_NAME = 15  # prctl(2): the process's name in /proc/PID/comm, ps -e and top


def script_of(entity: OperationEntity) -> tuple[str, Path]:
    """The entity's lot script: (script_id, path), the lot's own script or else its product's (as the Lot
    Server's answer to the attach named it)."""
    if entity.script_id is None or entity.script_path is None:
        raise LotError(
            f"entity {entity.entity_id}: its lot and product name no lot script "
            "(register one with `gwc script register`)"
        )
    return entity.script_id, resolve_path(entity.script_path)


def resolve_path(path: str) -> Path:
    """LOT_SCRIPTS.path: absolute, or relative to the project (the shipped scripts)."""
    p = Path(path)
    return p if p.is_absolute() else PROJECT_ROOT / p


def load_script(path: Path) -> ModuleType:
    """Import a lot script file and check it has `main(entity)`."""
    if not path.is_file():
        raise LotError(f"lot script {path} does not exist")
    try:
        check_trusted_file(path, "lot script")  # run as the cell's user: written by it or root alone
    except NotPrivate as e:
        raise LotError(str(e)) from None
    spec = importlib.util.spec_from_file_location(f"gwc_lot_script_{path.stem}", path)
    if spec is None or spec.loader is None:
        raise LotError(f"cannot load lot script {path}")
    module = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(module)
    except Exception as e:
        raise LotError(f"lot script {path} failed to load: {type(e).__name__}: {e}") from e
    if not callable(getattr(module, "main", None)):
        raise LotError(f"lot script {path} has no main(entity) function")
    return module


class Forked:
    """A lot script process this one started (forked, or exec'd: `popen`), waited for as a Popen is;
    its CPU known once it ended."""

    def __init__(self, pid: int, popen: subprocess.Popen[bytes] | None = None) -> None:
        self.pid = pid
        self.popen = popen  # held, so that no Popen finalizer reaps it first
        self.cpu_s: float | None = None

    def wait(self) -> int:
        """Reap it (blocks while it runs); its exit code, minus the signal that killed it."""
        _, status, usage = os.wait4(self.pid, 0)
        self.cpu_s = usage.ru_utime + usage.ru_stime
        code = os.waitstatus_to_exitcode(status)
        if self.popen is not None:
            self.popen.returncode = code
        return code


def exec_lot_script(cfg: Config, entity_id: int, user: LotUser, gate: int | None = None) -> Forked:
    """Start entity E's lot script as the lot user (gwc.hostuser): a fresh `python -m gwc.lot.run`, exec'd,
    holding nothing of the agent's (a fork would carry the module key in its memory), its uid and gid
    the lot user's and no other group. What it writes is made for it first: its log (0660, the lot
    user's group; moved aside past the cap, which the script cannot do in var/log) and its .out (opened
    here); var/ passable, lot.key readable, var/lots writable (gwc.private.share_with_lot_user).

    `gate`: the read end of a pipe the script waits on before it does anything (`--gate`), started
    ahead of its claim (gwc/agent/lot_hosts.py): no pid file until the agent adopts it."""
    base = lot_proc(entity_id)
    gated = ("--gate", str(gate)) if gate is not None else ()
    proc = Proc(base.kind, base.machine, command=(*base.command, "--var", str(cfg.var.resolve()), *gated))
    make_lot_log(cfg, entity_id, user)
    env = {CELL_UID_ENV: f"{os.geteuid()}:{os.getegid()}"}
    fds = (gate,) if gate is not None else ()
    popen = spawn_process(cfg, proc, env, pass_fds=fds, user=(user.uid, user.gid), record=gate is None)
    return Forked(popen.pid, popen)


def make_lot_log(cfg: Config, entity_id: int, user: LotUser) -> None:
    """Make entity E's log for a script of the lot user (who may not make files in var/log): 0660 with
    its group, moved aside first past the size cap (which the script cannot do)."""
    secure_var(cfg)
    log = cfg.log_dir / log_file_name(lot_proc(entity_id).name)
    with contextlib.suppress(FileNotFoundError):
        if log.lstat().st_size >= MAX_LOG_BYTES:
            log.replace(log.with_name(log.name + ".1"))
    make_lot_file(log, user.gid)


def fork_lot_script(cfg: Config, entity_id: int) -> Forked:
    """Start entity E's lot script as a child of this process, a fork of it: what `python -m gwc.lot.run
    --entity E` would be (own session, pid file, .out file, the cell's environment), without the fresh
    interpreter's 0.3 s of imports. For the agent, which holds no thread that the fork would lose:
    the child is this process's copy of one thread, its loop, sockets and files all dropped."""
    proc = lot_proc(entity_id)
    cfg.log_dir.mkdir(parents=True, exist_ok=True)
    out = open_out(out_file(cfg, proc.name))
    for stream in (sys.stdout, sys.stderr):  # nothing of ours written twice, once by the child
        stream.flush()
    inherited = open_files()
    try:
        pid = os.fork()
        if pid == 0:
            fork_child(cfg, entity_id, out, inherited)
    finally:
        os.close(out)
    write_pid_file(cfg, proc.name, pid, proc.argv)
    return Forked(pid)


def open_files() -> dict[int, str]:
    """This process's file descriptors and what each is open on (/proc/self/fd: a path, socket:[inode] ...)."""
    files = {}
    for fd in os.listdir("/proc/self/fd"):
        with contextlib.suppress(OSError):  # the listing's own descriptor, gone already
            files[int(fd)] = os.readlink(f"/proc/self/fd/{fd}")
    return files


def shed(inherited: dict[int, str]) -> None:
    """Close every descriptor above stderr that is still what the parent had open (`inherited`): its
    sockets, pidfds, lock and loop. Not a blanket close: a fork handler may have opened descriptors
    of the child's own, and libuv's does (the agent's loop is uvloop's: its signal lock pipe is made
    anew in the child, at the same numbers); closed, libuv would read and write whatever reused them."""
    for fd, what in open_files().items():
        if fd > 2 and inherited.get(fd) == what:
            os.close(fd)


def fork_child(cfg: Config, entity_id: int, out: int, inherited: dict[int, str]) -> NoReturn:
    """The forked child: shed what it inherited, run the entity, exit without returning into the parent's code."""
    code = 1
    try:
        # The parent's objects stay as they are, never collected: a finalizer would close a file
        # descriptor number this process has since reused.
        gc.freeze()
        os.setsid()
        # Its command line is the agent's: its name tells it apart (`ps -e`, top, gwc bench cell).
        ctypes.CDLL(None).prctl(PR_SET_NAME, lot_proc(entity_id).name.encode()[:15], 0, 0, 0)
        signal.set_wakeup_fd(-1)
        for sig in (signal.SIGTERM, signal.SIGHUP, signal.SIGCHLD):
            signal.signal(sig, signal.SIG_DFL)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        null = os.open(os.devnull, os.O_RDONLY)
        os.dup2(null, 0)
        os.dup2(out, 1)
        os.dup2(out, 2)
        os.close(null)
        shed(inherited)  # `out` with the rest
        os.environ.update(process_env(cfg))
        os.chdir(cfg.var)
        code = run_entity(cfg, entity_id)
    except BaseException:  # never back into the parent's code: this process is the lot's
        traceback.print_exc()
    finally:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        os._exit(code)


def _stop(signum: int, frame: FrameType | None) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # one is enough: clean up undisturbed
    raise ScriptStopped(f"stopped by signal {signal.Signals(signum).name}")


def run_entity(cfg: Config, entity_id: int) -> int:
    """Run entity E's lot script to its end; the process's exit code."""
    log = open_log(f"lot:{entity_id}", cfg.log_dir, cfg.level_of(f"lot:{entity_id}"))
    if not os.access(cfg.log_dir, os.W_OK):  # the lot user: the agent moves its log aside at its start
        for handler in log.handlers:
            if isinstance(handler, CappedFileHandler):
                handler.maxBytes = 0
    cap_output()
    log.info("lot script process for entity %d starting (pid %d)", entity_id, os.getpid())
    signal.signal(signal.SIGTERM, _stop)
    # The script and its bus thread hand the GIL back and forth at every step: with the default 5 ms
    # switch interval, a bus thread woken while the script runs Python would answer that much later.
    sys.setswitchinterval(SWITCH_INTERVAL)
    try:
        with OperationEntity(cfg, entity_id, log) as entity:
            script_id, path = script_of(entity)
            log.info("running lot script %s (%s)", script_id, path)
            entity.traveller.update(script_id=script_id)
            script = load_script(path)
            gc.freeze()  # start-up's objects live as long as the process: out of the collector's way
            script.main(entity)
    except GwcError as e:
        log.error("lot script of entity %d ended: %s", entity_id, e)
        return e.exit_code
    except Exception:
        log.exception("lot script of entity %d crashed", entity_id)
        return 1
    finally:
        _forget_pid_file(cfg, entity_id)
    log.info("lot script of entity %d finished", entity_id)
    return 0


def _forget_pid_file(cfg: Config, entity_id: int) -> None:
    """The process is ending: its pid file (written by whoever spawned it) goes with it."""
    path = pid_file(cfg, f"lot:{entity_id}")
    with contextlib.suppress(OSError, ValueError, KeyError):
        if json.loads(path.read_text())["pid"] == os.getpid():
            path.unlink()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m gwc.lot.run", description=__doc__.split("\n\n")[0])
    parser.add_argument("--entity", type=int, required=True, help="the operation entity (LOT_STATUS.entity_id)")
    parser.add_argument("--var", help="the cell's var/ (the agent names it: `gwc stop` knows its scripts by it)")
    parser.add_argument("--gate", type=int, help="wait for 'g' on this descriptor first (EOF: exit, touching nothing)")
    args = parser.parse_args(argv)
    try:
        cfg = load_config()
        if args.var and Path(args.var).resolve() != cfg.var.resolve():
            raise ConfigError(f"--var {args.var} is not this cell's var/ ({cfg.var})")
    except GwcError as e:
        print(f"gwc.lot.run: {e}", file=sys.stderr)
        return e.exit_code
    if args.gate is not None and not opened(args.gate):
        return 0
    return run_entity(cfg, args.entity)


def opened(gate: int) -> bool:
    """A script started ahead of its claim (exec_lot_script's `gate`): interpreter up, imports done,
    nothing touched. True once its agent claimed the entity and said go; False when the agent let it
    go (the pipe closed: another host claimed it, or its own host came back)."""
    with os.fdopen(gate, "rb", buffering=0) as pipe:
        return pipe.read(1) == b"g"


if __name__ == "__main__":
    sys.exit(main())
