"""The end-to-end test harness: a private cell (own bus group and port, own var/, own database)
whose modules are real processes started through pytest-xprocess, and an observer on its bus.

Readiness is proven by a real probe (the module's hello on the bus, with the interest it has once
started), never by a bare sleep; everything started is terminated at close, even when a test fails.
"""

from __future__ import annotations

import os
import random
import signal
import sys
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any, TypeVar

import psycopg
from xprocess import ProcessStarter

from gwc.cell import write_pid_file
from gwc.config import Config
from gwc.ipc import BlockingBus
from gwc.log import log_file_name, open_log
from gwc.me.cmm_sim import simulated
from gwc.module import module_name
from gwc.soak.private_config import private_bus, write_config

T = TypeVar("T")
SERVERS = ("cas", "ers", "ms", "ls", "sls", "msched")
STOP_CLASS = {"wc": "ME_SHUT"}


def wait_for(predicate: Callable[[], T], timeout: float = 10.0, what: str = "condition", interval: float = 0.02) -> T:
    """Poll until predicate() is truthy; fail the test naming `what` after the deadline."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:.1f}s waiting for {what}")
        time.sleep(interval)


async def until(pause: Callable[[float], Awaitable[Any]], predicate: Callable[[], T], timeout: float, what: str) -> T:
    """wait_for on an event loop that must keep running meanwhile (a Textual pilot: `until(pilot.pause, ...)`)."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:.1f}s waiting for {what}")
        await pause(0.05)


def write_cell_config(
    var: Path,
    database_url: str | None,
    machines: list[dict[str, Any]] = (),  # type: ignore[assignment]
    modules: tuple[str, ...] = SERVERS,
    policy: str = "fifo",
    bus: dict[str, Any] | None = None,
    faults: dict[str, Any] | None = None,
    level: str = "note",
    sections: dict[str, Any] | None = None,
    record: dict[str, Any] | None = None,
) -> Config:
    """Write var/etc/cell.toml for a private cell with a random multicast group and port (`sections`:
    more tables, e.g. {"lots": {"max_running": 4}})."""
    bus_cfg = private_bus(peer_timeout=1.5, heartbeat=0.2, **(bus or {}))
    if faults:
        bus_cfg["faults"] = faults
    return write_config(
        var / "etc" / "cell.toml",
        {
            "cell": {"name": "test", "var": str(var), "policy": policy},
            "bus": bus_cfg,
            "database": {"url": database_url or ""},
            "log": {"level": level},
            "module": [{"name": m} for m in modules],
            "machine": list(machines),
            **(sections or {}),
            **({"record": record} if record else {}),
        },
    )


class CellHarness:
    """A private cell for one test. Use through the `cell` fixture (tests/e2e/conftest.py)."""

    def __init__(self, xprocess: Any, var: Path, database_url: str | None, **config: Any) -> None:
        self.xprocess = xprocess
        self.var = var
        self.cfg = write_cell_config(var, database_url, **config)
        self.database_url = database_url
        self.tag = f"t{os.getpid()}-{random.randrange(1 << 30):x}"
        self.started: list[str] = []
        self.log = open_log("test", self.cfg.log_dir, "trace")
        self.bus = BlockingBus(f"test.{os.getpid()}.{self.tag}", self.cfg.bus, self.log)

    # ----------------------------------------------------------------- processes

    def env(self) -> dict[str, str]:
        env = dict(os.environ, GWC_CONFIG=str(self.cfg.path), GWC_VAR=str(self.var), PYTHONUNBUFFERED="1")
        if self.database_url:
            env["GWC_DATABASE_URL"] = self.database_url
        return env

    def _xname(self, name: str) -> str:
        return f"{self.tag}-{name.replace(':', '-')}"

    def start(
        self,
        kind: str,
        machine: str | None = None,
        start: bool = True,
        timeout: float = 20.0,
        extra_args: tuple[str, ...] = (),
    ) -> int:
        """Start one module as a process; return its pid once it is on the bus (and started, if asked)."""
        name = module_name(kind, machine)
        harness = self
        on_bus = kind not in ("me", "cmmsim")
        args = [
            sys.executable,
            "-m",
            "gwc",
            "run",
            kind,
            *(["--machine", machine] if machine else []),
            *(["--start"] if start and on_bus else []),
            *extra_args,
        ]

        class Starter(ProcessStarter):
            env = harness.env()
            terminate_on_interrupt = True
            max_read_lines = 200

            def __init__(self, control_dir: Any, process: Any) -> None:
                super().__init__(control_dir, process)
                self.timeout = timeout

            @property
            def args(self) -> list[str]:  # type: ignore[override]
                return args

            def startup_check(self) -> bool:
                if not on_bus:
                    return harness.log_has(name, "Starting")
                peer = harness.bus.peers().get(name)
                if peer is None:
                    return False
                return not start or STOP_CLASS.get(kind, "SHUTDOWN") in peer.interest

        pid, _ = self.xprocess.ensure(self._xname(name), Starter, restart=True)
        write_pid_file(self.cfg, name, int(pid), args)  # as gwc start does: `gwc machine start` reads it
        if name not in self.started:
            self.started.append(name)
        return int(pid)

    def pid(self, kind: str, machine: str | None = None) -> int | None:
        return self.xprocess.getinfo(self._xname(module_name(kind, machine))).pid

    def alive(self, kind: str, machine: str | None = None) -> bool:
        return bool(self.xprocess.getinfo(self._xname(module_name(kind, machine))).isrunning())

    def kill(self, kind: str, machine: str | None = None, sig: int = signal.SIGKILL) -> None:
        """Signal one module (kill -9 by default) and wait until it is gone."""
        info = self.xprocess.getinfo(self._xname(module_name(kind, machine)))
        if info.pid:
            try:
                os.kill(info.pid, sig)
            except ProcessLookupError:
                return
            wait_for(lambda: not info.isrunning(), 10, f"{module_name(kind, machine)} to die")

    def start_servers(self, *names: str) -> None:
        for n in names or SERVERS:
            self.start(n)

    def start_machine_processes(self, machine: str) -> None:
        """Start a machine's processes (simulator if any, ME, WC); the machine stays Shutdown."""
        spec = self.cfg.machine(machine)
        if simulated(spec):
            self.start("cmmsim", machine)
        self.start("me", machine)
        self.start("wc", machine, start=False)

    def close(self) -> None:
        """Terminate every process, remove queues and pty links, leave the bus. Never raises."""
        for name in reversed(self.started):
            try:
                self.xprocess.getinfo(self._xname(name)).terminate(timeout=10)
            except Exception as e:  # keep cleaning the rest
                print(f"harness: terminating {name} failed: {e}")
        try:
            from gwc.cell import clean_machine_state

            clean_machine_state(self.cfg, [m.id for m in self.cfg.machines])
        except Exception as e:
            print(f"harness: cleaning machine state failed: {e}")
        self.bus.close()

    # ----------------------------------------------------------------- looking at the cell

    def log_path(self, name: str) -> Path:
        return self.cfg.log_dir / log_file_name(name)

    def log_text(self, name: str) -> str:
        try:
            return self.log_path(name).read_text(errors="replace")
        except OSError:
            return ""

    def log_has(self, name: str, text: str) -> bool:
        return text in self.log_text(name)

    def db(self) -> psycopg.Connection:
        """A superuser connection for the test to look at (never to act for a module)."""
        assert self.database_url
        return psycopg.connect(self.database_url, autocommit=True)

    def query(self, sql: str, *params: Any) -> list[tuple[Any, ...]]:
        with self.db() as conn:
            return conn.execute(sql, params).fetchall()
