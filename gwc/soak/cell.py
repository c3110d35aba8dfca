"""A private cell for the soak and the whole-cell benchmark: its own var/, bus group, queues, database.

It is the operator's cell in miniature, started and stopped with the same gwc.cell functions
`gwc start` / `gwc stop` use, plus what chaos needs: kill -9 one process, restart it (with the bus
fault injector on, if asked), and, at the end, a list of whatever the cell left behind. With
`agent=True` (as `gwc start` runs a cell) the host's agent starts the modules and restarts the ones
killed; restart() then only makes sure the agent has the module running.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import signal
import stat
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from types import FrameType
from typing import Any

from gwc import db
from gwc.agent import control as agent_control
from gwc.cell import (
    Proc,
    cell_procs,
    hi_bus,
    pid_file,
    read_pid,
    spawn,
    start_agent,
    start_procs,
    startup,
    stop_cell,
    wait_on_bus,
)
from gwc.config import SERVER_MODULES, Config
from gwc.errors import GwcError, ModuleError
from gwc.ipc import BlockingBus
from gwc.ipc.mq import queue_exists, queue_names
from gwc.ipc.names import Conv
from gwc.retry import Deadline
from gwc.soak.private_config import private_bus, write_config

UP_TIMEOUT = 30.0  # a restarted module must be back on the bus within this (machines are shared and busy)
HI_TIMEOUT = 60.0  # one `gwc machine start|stop` command


def config_doc(
    var: Path,
    database_url: str | None,
    machines: list[dict[str, Any]],
    policy: str,
    bus: dict[str, Any],
    faults: dict[str, Any] | None = None,
    db_settings: dict[str, Any] | None = None,
    record: dict[str, Any] | None = None,
    lots: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """cell.toml of a private cell; the same document with `faults` is the fault-injected variant."""
    database: dict[str, Any] = {"url": database_url or ""}
    if db_settings:
        database["settings"] = db_settings
    return {
        "cell": {"name": "private", "var": str(var), "policy": policy},
        # The keys named, not left to var: a process given another GWC_VAR (a console a bench opens on
        # this cell) still signs with this cell's key.
        "bus": {
            "key_file": str(var / "secrets" / "cell.key"),
            "lot_key_file": str(var / "secrets" / "lot.key"),
            **bus,
            **({"faults": faults} if faults else {}),
        },
        "database": database,
        "log": {"level": "note"},
        "module": [{"name": m} for m in SERVER_MODULES],
        "machine": machines,
        **({"record": record} if record else {}),
        **({"lots": lots} if lots else {}),
    }


def _exit_on_sigterm(signum: int, frame: FrameType | None) -> None:
    sys.exit(128 + signum)


class PrivateCell:
    """A whole cell (servers, MSCHED, dummy machines) under `var`, on a bus group of its own."""

    def __init__(
        self,
        var: Path,
        machines: list[dict[str, Any]],
        log: logging.Logger,
        database_url: str | None = None,
        policy: str = "priority",
        db_settings: dict[str, Any] | None = None,
        bus: dict[str, Any] | None = None,
        agent: bool = False,
        record: dict[str, Any] | None = None,
        lots: dict[str, Any] | None = None,
    ) -> None:
        self.var = var.resolve()
        self.agent = agent
        self.log = log
        self.machines = [m["id"] for m in machines]
        # Not the soak's seed: two soaks of one seed may run side by side. The shipped timers (heartbeat,
        # peer_timeout): soaks and `bench cell` measure the cell as it is run.
        self._bus_cfg = private_bus(**(bus or {}))
        self._text_args: dict[str, Any] = dict(
            var=self.var,
            database_url=database_url,
            machines=machines,
            policy=policy,
            db_settings=db_settings,
            record=record,
            lots=lots,
        )
        written = write_config(self.var / "etc" / "cell.toml", config_doc(bus=self._bus_cfg, **self._text_args))
        if (lots or {}).get("user"):  # scripts of a user of their own read the configuration too
            written.path.parent.chmod(0o711)
            written.path.chmod(0o644)
        # Its own var/, whatever GWC_VAR says: that names the operator's cell, whose pid files this one's would
        # overwrite. Its processes are given GWC_VAR=var (env(), spawn()).
        self.cfg: Config = dataclasses.replace(written, var=self.var)
        self.bus: BlockingBus | None = None
        self._sigterm: signal.Handlers | Callable[[int, FrameType | None], Any] | int | None = None

    # ----------------------------------------------------------------- whole cell

    def start(self, start_machines: bool = True) -> None:
        """Database, schema, every process (servers through STARTUP), then each machine (ME_START)."""
        if threading.current_thread() is threading.main_thread():
            # `timeout`, `kill`: unwind as Ctrl-C does, so that the owner's `finally: stop()` runs. Python's
            # default SIGTERM ends the process where it stands, and left the whole cell running behind it.
            self._sigterm = signal.signal(signal.SIGTERM, _exit_on_sigterm)
        if self.cfg.embedded:
            db.cluster_start(self.cfg, self.log)
        db.init_schema(self.cfg, self.log)
        self.bus = hi_bus(self.cfg, self.log)
        if self.agent:
            start_agent(self.cfg, self.log.info)
        start_procs(self.cfg, cell_procs(self.cfg), self.bus, self.log.info)
        if start_machines:
            for m in self.machines:
                self.machine_start(m, via_hi=False)

    def stop(self) -> None:
        """Everything the cell runs, stopped as `gwc stop` does (lot scripts first). Never raises."""
        try:
            stop_cell(self.cfg, self.log, say=self.log.info, database=self.cfg.embedded)
        except GwcError as e:
            self.log.error("stopping the private cell: %s", e)
        if self.bus is not None:
            self.bus.close()
            self.bus = None
        if self._sigterm is not None:  # the process's own handler again
            signal.signal(signal.SIGTERM, self._sigterm)
            self._sigterm = None

    def env(self, config: Path | None = None) -> dict[str, str]:
        env = dict(os.environ, GWC_CONFIG=str(config or self.cfg.path), GWC_VAR=str(self.var), PYTHONUNBUFFERED="1")
        if self.cfg.database_url:
            env["GWC_DATABASE_URL"] = self.cfg.database_url
        return env

    # ----------------------------------------------------------------- one process

    def kill(self, name: str) -> int | None:
        """kill -9 one process (its whole process group); returns its pid, None if it was not running."""
        st = read_pid(self.cfg, name)
        if not st.alive or st.pid is None:
            return None
        try:
            os.killpg(st.pid, signal.SIGKILL)
        except ProcessLookupError:
            return st.pid
        deadline = Deadline(10)
        while (now := read_pid(self.cfg, name)).alive and now.pid == st.pid and not deadline.expired:
            time.sleep(0.02)
        if read_pid(self.cfg, name).pid == st.pid:  # not the pid file of an agent's restart since
            pid_file(self.cfg, name).unlink(missing_ok=True)
        return st.pid

    def faults_config(self, seed: int, faults: dict[str, float]) -> Path:
        """A copy of cell.toml with the bus fault injector on (seeded), for one restarted process."""
        path = self.var / "etc" / f"cell-faults-{seed}.toml"
        write_config(path, config_doc(bus=self._bus_cfg, faults={**faults, "seed": seed}, **self._text_args))
        return path

    def restart(self, name: str, config: Path | None = None) -> int:
        """Start one process again and bring it up: a server through STARTUP, a WC onto the bus."""
        assert self.bus is not None
        if self.agent:
            if config is None:  # the agent restarted it, or brings it up now (BACKOFF, FATAL, STOPPED)
                agent_control.call(self.cfg, "start", names=[name])
                return int(read_pid(self.cfg, name).pid or 0)
            agent_control.call(self.cfg, "stop", names=[name])  # off its watch while it runs with faults
        kind, _, machine = name.partition(":")
        old = self.bus.peers().get(name)
        extra = {"GWC_CONFIG": str(config)} if config else None
        pid = spawn(self.cfg, Proc(kind, machine or None), extra)
        if kind in ("me", "cmmsim"):
            return pid
        deadline = Deadline(UP_TIMEOUT)
        while True:  # the new incarnation, not the dead one the bus still remembers
            peer = self.bus.peers().get(name)
            if peer is not None and (old is None or peer.inc != old.inc):
                break
            if deadline.expired:
                raise ModuleError(f"{name} (pid {pid}) did not come back on the bus within {UP_TIMEOUT:.0f}s")
            if not read_pid(self.cfg, name).alive:
                wait_on_bus(self.cfg, self.bus, name, 0.0)  # raises with the tail of its .out
            time.sleep(0.02)
        if kind != "wc":
            startup(self.bus, name, timeout=UP_TIMEOUT)
        return pid

    def machine_start(self, machine: str, via_hi: bool = True) -> str:
        """Bring a machine up (ME_START): through the operator's `gwc machine start`, or directly."""
        if via_hi:
            return self.hi("machine", "start", machine)
        assert self.bus is not None
        return startup(self.bus, f"wc:{machine}", Conv.ME_START, timeout=UP_TIMEOUT)

    def hi(self, *args: str) -> str:
        """Run one Human Interface command against this cell; its output. ModuleError if it fails."""
        try:
            r = subprocess.run(
                [sys.executable, "-m", "gwc", *args],
                env=self.env(),
                capture_output=True,
                text=True,
                timeout=HI_TIMEOUT,
                cwd=str(self.var),
            )
        except subprocess.TimeoutExpired:
            raise ModuleError(f"gwc {' '.join(args)} did not finish within {HI_TIMEOUT:.0f}s") from None
        out = (r.stdout + r.stderr).strip().replace("\n", " | ")
        if r.returncode != 0:
            raise ModuleError(f"gwc {' '.join(args)} failed (exit {r.returncode}): {out}")
        return out

    def alive(self, name: str) -> bool:
        return read_pid(self.cfg, name).alive

    # ----------------------------------------------------------------- what is left behind

    def pids(self) -> dict[int, str]:
        """Live processes started for this cell (found by the GWC_VAR their environment carries): pid -> command."""
        mark = f"GWC_VAR={self.cfg.var.resolve()}".encode()  # what spawn() gives them (GWC_VAR wins over var)
        found = {}
        for d in Path("/proc").iterdir():
            if not d.name.isdigit() or int(d.name) == os.getpid():
                continue
            try:
                if mark not in (d / "environ").read_bytes().split(b"\0"):
                    continue
                fields = (d / "stat").read_text().rsplit(")", 1)[1].split()
                if fields[0] == "Z":
                    continue
                cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
            except OSError:
                continue
            found[int(d.name)] = cmd
        return found

    def processes(self) -> list[str]:
        """Live processes started for this cell, as "pid N: command"."""
        return [f"pid {pid}: {cmd}" for pid, cmd in self.pids().items()]

    def leaks(self) -> list[str]:
        """Processes, queues, pid files, sockets, pty links and stray files the stopped cell left."""
        left = [f"process {p}" for p in self.processes()]
        for m in self.machines:
            left += [f"queue {q}" for q in queue_names(self.cfg.ipc_prefix, m) if queue_exists(q)]
        mq = Path("/dev/mqueue")
        if mq.is_dir():
            left += [
                f"queue /{p.name}"
                for p in mq.iterdir()
                if p.name.startswith(self.cfg.ipc_prefix[1:]) and f"queue /{p.name}" not in left
            ]
        if self.cfg.embedded and db.cluster_running(self.cfg):
            left.append(f"database cluster in {self.cfg.pg_dir} still running")
        run = self.cfg.run_dir
        if run.is_dir():
            for p in sorted(run.iterdir()):
                try:
                    mode = p.lstat().st_mode
                except OSError:
                    continue
                if p.suffix in (".pid", ".pty", ".tmp") or stat.S_ISSOCK(mode):
                    left.append(f"file {p}")
        for folder in (self.cfg.results_dir,):
            if folder.is_dir():
                left += [f"file {p}" for p in sorted(folder.rglob("*")) if p.is_file()]
        left += [f"file {p}" for p in sorted(self.var.rglob("*.tmp")) if self.cfg.pg_dir not in p.parents]
        return left
