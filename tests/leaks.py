"""What a test leaves behind: processes, POSIX queues, sockets, database clusters (pymodbus's conftest
fails a test that leaves threads or transports; we do the same for what a cell is made of).

Every test runs with GWC_TEST_ID=<unique> in its environment, which every process it starts inherits
(detached ones too: lot scripts, modules, pg_ctl's postgres), so a process left running is found by
that mark, wherever its files are. Queues and clusters are found through the cell configurations
the test wrote under its tmp_path; sockets by the test process's own descriptors.
"""

from __future__ import annotations

import gc
import os
import signal
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from gwc import db
from gwc.config import Config, load_config
from gwc.errors import GwcError
from gwc.ipc.mq import queue_exists, queue_names

MARK = "GWC_TEST_ID"
SESSION = "GWC_TEST_SESSION"  # the same idea for the whole pytest run, for kill_on_termination
# The interpreter's own helpers, started once by the first test that uses multiprocessing: not a leak.
HELPERS = ("multiprocessing.resource_tracker", "multiprocessing.forkserver")
# Where a test's cells keep their configuration: tmp_path/etc, tmp_path/<cell>/etc, one more level.
CONFIGS = ("etc/cell.toml", "*/etc/cell.toml", "*/*/etc/cell.toml")


class Leaked(AssertionError):
    """A test left something of the cell behind."""


def marked_processes(mark: str, var: str = MARK) -> dict[int, str]:
    """Live processes (not zombies) whose environment carries var=mark (GWC_TEST_ID=mark): pid -> command line."""
    needle = f"{var}={mark}".encode()
    found = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit() or int(d.name) == os.getpid():
            continue
        try:
            if needle not in (d / "environ").read_bytes().split(b"\0"):
                continue
            if (d / "stat").read_text().rsplit(")", 1)[1].split()[0] == "Z":
                continue
            cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
        except (OSError, IndexError):
            continue
        if not any(h in cmd for h in HELPERS):
            found[int(d.name)] = cmd
    return found


def open_files(pid: int | str = "self") -> set[str]:
    """What a process's descriptors point at: files by path, sockets as socket:[inode]. A descriptor closed
    between the listing and the read is skipped: a running process's descriptors change under the reader."""
    out = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            out.add(os.readlink(fd))
        except OSError:
            continue
    return out


def sockets() -> set[str]:
    """This process's open sockets (their inodes)."""
    return {t for t in open_files() if t.startswith("socket:")}


def cell_configs(root: Path) -> list[Config]:
    """The cell configurations a test wrote under `root` (unreadable ones skipped)."""
    found = []
    for pattern in CONFIGS:
        for path in sorted(root.glob(pattern)):
            try:
                found.append(load_config(path))
            except GwcError:
                continue
    return found


def left_by_cells(root: Path) -> list[str]:
    """Queues and running embedded clusters of the cells configured under `root`."""
    left = []
    for cfg in cell_configs(root):
        for m in cfg.machines:
            left += [f"queue {q}" for q in queue_names(cfg.ipc_prefix, m.id) if queue_exists(q)]
        if cfg.embedded and db.cluster_running(cfg):
            left.append(f"database cluster in {cfg.pg_dir}")
    return left


def _kill(pids: dict[int, str]) -> None:
    for pid in pids:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def kill_on_termination() -> None:
    """Mark every process this pytest run starts, and kill them all if the run is terminated (SIGTERM,
    SIGHUP: a CI timeout, a closed terminal), when no fixture's teardown runs. Call in the controller
    only: a pytest-xdist worker would kill its siblings."""
    os.environ.setdefault(SESSION, uuid.uuid4().hex)

    def terminated(signum: int, frame: object) -> None:
        _kill(marked_processes(os.environ[SESSION], SESSION))
        signal.signal(signum, signal.SIG_DFL)
        os.kill(os.getpid(), signum)

    for sig in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, terminated)


@contextmanager
def unmarked() -> Iterator[None]:
    """Start what outlives the test (a session fixture's process) without the test's mark."""
    mark = os.environ.pop(MARK, None)
    try:
        yield
    finally:
        if mark is not None:
            os.environ[MARK] = mark


@contextmanager
def leak_check(root: Path) -> Iterator[None]:
    """Run the body with a fresh GWC_TEST_ID; then raise Leaked naming what is left (and kill leaked
    processes, so one test's leak does not fail the next)."""
    mark = uuid.uuid4().hex
    before = sockets()
    old = os.environ.get(MARK)
    os.environ[MARK] = mark
    try:
        yield
    finally:
        if old is None:
            os.environ.pop(MARK, None)
        else:
            os.environ[MARK] = old
    procs = marked_processes(mark)
    left = [f"process {pid}: {cmd}" for pid, cmd in sorted(procs.items())]
    left += left_by_cells(root)
    extra = sockets() - before
    if extra:
        gc.collect()  # a socket dropped but not yet collected is closed now; one still referenced is a leak
        extra = sockets() - before
    left += [f"open {s}" for s in sorted(extra)]
    _kill(procs)
    if left:
        raise Leaked("the test left behind: " + "; ".join(left))
