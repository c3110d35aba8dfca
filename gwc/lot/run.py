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
import sys
import traceback
from pathlib import Path
from types import FrameType, ModuleType
from typing import NoReturn

from gwc.cell import lot_proc, out_file, pid_file, process_env, write_pid_file
from gwc.config import PROJECT_ROOT, Config, load_config
from gwc.errors import GwcError
from gwc.log import cap_output, open_log, open_out
from gwc.lot.entity import OperationEntity
from gwc.lot.errors import LotError, ScriptStopped
from gwc.lot.spawn import spawn_lot_script as spawn_lot_script  # (re-exported: gwc.client.orders, gwc.soak, gwc.bench)
from gwc.lot.spawn import spawn_lot_scripts as spawn_lot_scripts
from gwc.private import NotPrivate, check_trusted_file

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
    """A lot script process this one forked, waited for as a Popen is; its CPU known once it ended."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.cpu_s: float | None = None

    def wait(self) -> int:
        """Reap it (blocks while it runs); its exit code, minus the signal that killed it."""
        _, status, usage = os.wait4(self.pid, 0)
        self.cpu_s = usage.ru_utime + usage.ru_stime
        return os.waitstatus_to_exitcode(status)


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
            _forked(cfg, entity_id, out, inherited)
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


def _forked(cfg: Config, entity_id: int, out: int, inherited: dict[int, str]) -> NoReturn:
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
    args = parser.parse_args(argv)
    try:
        cfg = load_config()
    except GwcError as e:
        print(f"gwc.lot.run: {e}", file=sys.stderr)
        return e.exit_code
    return run_entity(cfg, args.entity)


if __name__ == "__main__":
    sys.exit(main())
