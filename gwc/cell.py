"""Cell start, stop and status: the successor of Listing 4's start.csh and Listing 5's stop.csh.

`start_cell` starts the embedded database (if used), applies the schema, then each configured
module as its own detached process with a pid file, in etc/cell.toml's order, and returns when each
has said it is up: a server by completing a STARTUP conversation, a machine's WC by appearing on the
bus (machines then wait, Shutdown, for the operator's `gwc machine start`). `stop_cell` stops
everything in reverse order, SIGTERM first, SIGKILL after a grace period, and removes every pid file,
message queue and pty link so that the next start finds a clean state. Both are idempotent.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

from gwc import db
from gwc.agent import control as agent_control
from gwc.config import Config
from gwc.errors import ConfigError, ModuleError
from gwc.hostuser import AGENT_CAPS, ambient
from gwc.ipc import BlockingBus, Bus, keys
from gwc.ipc.catalogue import message
from gwc.ipc.codes import AckCode
from gwc.ipc.names import Conv, Msg
from gwc.log import log_file_name, open_out
from gwc.me.cmm_sim import simulated
from gwc.module import module_name
from gwc.private import NotPrivate, not_the_cells, pid_info, secure_var, write_new
from gwc.retry import Deadline

GRACE = 5.0
EXITING = 1.0  # s a process refused as not the cell's may take to finish exiting (gwc stop, stop_proc)
REFUSED = "refused"  # how stop_proc's answer begins when a pid file named what is not the cell's
UP_TIMEOUT = 20.0


@dataclass(frozen=True)
class Proc:
    """One process of the cell: what to run and what to call it."""

    kind: str
    machine: str | None = None
    command: tuple[str, ...] = ()  # a process that is not a `gwc run` module (a lot script)

    @property
    def name(self) -> str:
        return module_name(self.kind, self.machine)

    @property
    def argv(self) -> list[str]:
        if self.command:
            return list(self.command)
        args = [sys.executable, "-m", "gwc", "run", self.kind]
        return args + (["--machine", self.machine] if self.machine else [])


def lot_proc(entity_id: int) -> Proc:
    """The process of one operation entity: its lot script (gwc/lot/run.py)."""
    return Proc("lot", str(entity_id), command=(sys.executable, "-m", "gwc.lot.run", "--entity", str(entity_id)))


def machine_procs(cfg: Config, machine_id: str) -> list[Proc]:
    """The processes of one machine in start order: simulator (if any), ME, then WC."""
    spec = cfg.machine(machine_id)
    procs = []
    if simulated(spec):
        procs.append(Proc("cmmsim", spec.id))
    return procs + [Proc("me", spec.id), Proc("wc", spec.id)]


def cell_procs(cfg: Config) -> list[Proc]:
    """Every process of the cell on this host, in start order (all of them in a one-host cell)."""
    procs = [Proc(m.name) for m in cfg.modules if cfg.placed_here(m) or cfg.standby_here(m)]
    for m in cfg.machines:
        if cfg.placed_here(m):
            procs += machine_procs(cfg, m.id)
    return procs


def pid_file(cfg: Config, name: str) -> Path:
    return cfg.run_dir / (log_file_name(name)[: -len(".log")] + ".pid")


def _proc_start_ticks(pid: int) -> int | None:
    """The kernel's start time of pid (field 22 of /proc/pid/stat): tells a reused pid from ours."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return int(stat.rsplit(")", 1)[1].split()[19])


def _zombie(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except OSError:
        return True


@dataclass(frozen=True)
class ProcStatus:
    name: str
    pid: int | None
    alive: bool
    since: str | None
    refused: str | None = None  # why the pid file is not believed (not the cell's: gwc.private)


def read_pid(cfg: Config, name: str) -> ProcStatus:
    path = pid_file(cfg, name)
    try:
        info = pid_info(path)
    except NotPrivate as e:
        return ProcStatus(name, None, False, None, str(e))
    if info is None:
        return ProcStatus(name, None, False, None)
    pid = int(info["pid"])
    alive = _proc_start_ticks(pid) == info.get("ticks") and not _zombie(pid)
    return ProcStatus(name, pid, alive, info.get("since"))


def out_file(cfg: Config, name: str) -> Path:
    """Where a process's output goes before its log opens (tracebacks of a failed start)."""
    return cfg.log_dir / (log_file_name(name)[: -len(".log")] + ".out")


def process_env(cfg: Config) -> dict[str, str]:
    """What a process of the cell finds in its environment: this cell's configuration, state and database."""
    env = {"GWC_CONFIG": str(cfg.path.resolve()), "GWC_VAR": str(cfg.var.resolve()), "PYTHONUNBUFFERED": "1"}
    if cfg.database_url:
        env["GWC_DATABASE_URL"] = cfg.database_url
    return env


def spawn_process(
    cfg: Config,
    proc: Proc,
    extra_env: dict[str, str] | None = None,
    pass_fds: tuple[int, ...] = (),
    user: tuple[int, int] | None = None,
    record: bool = True,
) -> subprocess.Popen[bytes]:
    """Start one module in a session of its own, with its pid file; output before its log opens goes to .out.
    `user`: (uid, gid) it runs as, with no other group (a lot script as the lot user: gwc.hostuser).
    `record` False: no pid file yet (a lot script started ahead of its claim writes it when claimed).

    The caller is its parent: the agent keeps the Popen to reap it; a command that exits leaves it to init."""
    secure_var(cfg)
    cfg.log_dir.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, **process_env(cfg), **(extra_env or {})}  # extra_env may name GWC_CONFIG again: it wins
    with os.fdopen(open_out(out_file(cfg, proc.name)), "ab") as out:
        child = subprocess.Popen(
            proc.argv,
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=out,
            start_new_session=True,
            cwd=str(cfg.var.resolve()),
            pass_fds=pass_fds,
            user=user[0] if user else None,
            group=user[1] if user else None,
            extra_groups=[] if user else None,
        )
    if record:
        write_pid_file(cfg, proc.name, child.pid, proc.argv)
    return child


def spawn(cfg: Config, proc: Proc, extra_env: dict[str, str] | None = None) -> int:
    """spawn_process() for a caller that only needs the pid."""
    return spawn_process(cfg, proc, extra_env).pid


def write_pid_file(cfg: Config, name: str, pid: int, argv: list[str]) -> None:
    info = {
        "pid": pid,
        "ticks": _proc_start_ticks(pid),
        "since": datetime.now().isoformat(" ", "seconds"),
        "argv": argv,
    }
    secure_var(cfg)
    write_new(pid_file(cfg, name), json.dumps(info).encode())


def _out_tail(cfg: Config, name: str, lines: int = 5) -> str:
    try:
        text = out_file(cfg, name).read_text(errors="replace")
    except OSError:
        return ""
    return " | ".join(text.strip().splitlines()[-lines:])


def wait_on_bus(cfg: Config, bus: BlockingBus, name: str, timeout: float = UP_TIMEOUT) -> None:
    """Wait until module `name` says hello on the bus, failing early if its process died."""
    deadline = Deadline(timeout)
    while not deadline.expired:
        if name in bus.peers():
            return
        st = read_pid(cfg, name)
        if st.pid is not None and not st.alive:
            raise ModuleError(f"{name} died at start: {_out_tail(cfg, name) or 'see ' + str(cfg.log_dir)}")
        time.sleep(0.05)
    raise ModuleError(f"{name} did not appear on the bus within {timeout:.0f}s (see {cfg.log_dir})")


async def hold_startup(bus: Bus, name: str, cls: str = Conv.STARTUP, timeout: float = UP_TIMEOUT) -> str:
    """Hold a STARTUP (or ME_START) conversation with one module; return how it ended."""
    conv, batch = await bus.request(cls, message(Msg.STARTUP_REQUEST, module=name), to=name, timeout=timeout)
    try:
        ack = batch.first
        if ack.ack_code == AckCode.NOTNOW:
            return "already started"
        if ack.ack_code != AckCode.ACK_OK:
            raise ModuleError(f"{name} refused startup: {ack.ack_code} {ack.note or ''}".strip())
        while True:
            done = (await conv.next_message(timeout)).first
            if done.name in (Msg.STARTUP_COMPLETE, Msg.ME_READY):
                if done.ack_code != AckCode.ACK_OK:
                    raise ModuleError(f"{name} startup failed: {done.ack_code} {done.note or ''}".strip())
                return "started"
    finally:
        conv.end()


def startup(bus: BlockingBus, name: str, cls: str = Conv.STARTUP, timeout: float = UP_TIMEOUT) -> str:
    """hold_startup() from a plain (non-asyncio) caller."""
    return bus.run(hold_startup(bus.bus, name, cls, timeout))


def shutdown(bus: BlockingBus, name: str, cls: str = Conv.SHUTDOWN, timeout: float = UP_TIMEOUT) -> str:
    conv, batch = bus.request(cls, message(Msg.SHUTDOWN_REQUEST, module=name), to=name, timeout=timeout)
    try:
        ack = batch.first
        if ack.ack_code == AckCode.NOTNOW:
            return "already shut down"
        if ack.ack_code != AckCode.ACK_OK:
            raise ModuleError(f"{name} refused shutdown: {ack.ack_code} {ack.note or ''}".strip())
        while True:
            done = conv.next_message(timeout).first
            if done.name in (Msg.SHUTDOWN_COMPLETE, Msg.ME_STOPPED):
                return "shut down" if done.ack_code == AckCode.ACK_OK else f"shut down with {done.ack_code}"
    finally:
        conv.end()


def hi_bus(cfg: Config, log: logging.Logger, interest: tuple[str, ...] = ()) -> BlockingBus:
    """The bus attachment of one Human Interface command (a unique name per process)."""
    return BlockingBus(f"hi.{os.getpid()}", cfg.bus, log, interest)


AGENT = Proc("agent", command=(sys.executable, "-m", "gwc", "agent"))


def start_procs(cfg: Config, procs: list[Proc], bus: BlockingBus, say: Callable[[str], None]) -> None:
    """Bring processes up in order (servers through STARTUP): through this host's agent when one runs,
    which then watches them; else spawn what is not running, unsupervised."""
    if agent_control.running(cfg):
        agent_control.call(cfg, "start", say=say, names=[p.name for p in procs])
        return
    for proc in procs:
        st = read_pid(cfg, proc.name)
        if st.alive:
            say(f"{proc.name}: already running (pid {st.pid})")
        else:
            pid = spawn(cfg, proc)
            say(f"{proc.name}: spawned (pid {pid})")
        if proc.kind in ("me", "cmmsim"):
            continue  # off the bus: their WC proves them
        wait_on_bus(cfg, bus, proc.name)
        if proc.kind == "wc":
            say(f"{proc.name}: on the bus (machine Shutdown until `gwc machine start {proc.machine}`)")
        else:
            say(f"{proc.name}: {startup(bus, proc.name)}")


def start_agent(cfg: Config, say: Callable[[str], None], timeout: float = UP_TIMEOUT) -> None:
    """Start this host's agent unless one runs (it adopts whatever modules are still running)."""
    if agent_control.running(cfg):
        return
    with ambient(AGENT_CAPS):  # the few it keeps of root's (gwc.hostuser): it clears them for what it starts
        pid = spawn(cfg, AGENT)
    say(f"agent: spawned (pid {pid})")
    deadline = Deadline(timeout)
    while not agent_control.running(cfg):
        if not read_pid(cfg, AGENT.name).alive:
            raise ModuleError(f"the agent died at start: {_out_tail(cfg, AGENT.name) or 'see ' + str(cfg.log_dir)}")
        if deadline.expired:
            raise ModuleError(f"the agent did not answer within {timeout:.0f}s (see {cfg.log_dir})")
        time.sleep(0.05)


def start_cell(cfg: Config, log: logging.Logger, say: Callable[[str], None] = print) -> None:
    """Database, schema, then the agent, which starts every module in order and keeps them running."""
    if cfg.embedded:
        db.cluster_start(cfg, log)
        say("database: embedded cluster running")
    if cfg.embedded or cfg.database_url:  # another host's embedded cluster is that host's to set up
        db.init_schema(cfg, log)
    if cfg.database_host is not None and not cfg.embedded and not Path(cfg.bus.key_file or "").exists():
        # A key made here would not be the cell's: the other hosts would refuse every datagram.
        raise ConfigError(
            f"no cell key at {cfg.bus.key_file}: copy var/secrets/ from {cfg.database_host.name} first "
            "(docs/deploying.md, Keys)"
        )
    if keys.ensure(cfg.bus):
        say(f"bus: new cell key in {cfg.bus.key_file} (copy it to the cell's other hosts: docs/security.md)")
    start_agent(cfg, say)
    agent_control.call(cfg, "start", say=say)


def signal_cells(cfg: Config, pid: int, sig: int) -> str | None:
    """Signal one of the cell's processes (its process group when it leads one, as everything the cell
    starts does); None once sent, else why it was not: a process that is not the cell's is never
    signalled, whatever a pid file says (gwc.private.not_the_cells)."""
    why = not_the_cells(cfg, pid)
    if why is not None:
        return why
    try:
        if os.getpgid(pid) == pid:
            os.killpg(pid, sig)
        else:
            os.kill(pid, sig)
    except ProcessLookupError:
        pass
    except PermissionError:  # a lot script of the lot user, and no CAP_KILL (`gwc stop` as the cell's user)
        return f"pid {pid} may not be signalled by uid {os.geteuid()}: stop the cell as root, or through its agent"
    return None


def stop_proc(cfg: Config, name: str, grace: float = GRACE) -> str:
    """SIGTERM, wait, SIGKILL; remove the pid file. Returns what happened."""
    st = read_pid(cfg, name)
    path = pid_file(cfg, name)
    if st.refused:
        path.unlink(missing_ok=True)
        return f"{REFUSED}: pid file not the cell's, removed unread ({st.refused})"
    if st.pid is None:
        path.unlink(missing_ok=True)
        return "not running"
    if not st.alive:
        path.unlink(missing_ok=True)
        return "was dead"
    how = "stopped"
    why = signal_cells(cfg, st.pid, signal.SIGTERM)
    if why is not None:
        # Told to go before (stop_cell signals every lot script first), it may be exiting: past the
        # release of its memory its command line and environment read empty, so it seems not the
        # cell's. Gone within a moment is stopped; only a process still alive after it was refused.
        gone = _gone_within(cfg, name, min(grace, EXITING))
        path.unlink(missing_ok=True)
        return "stopped" if gone else f"{REFUSED}: not signalled: {why} (pid file removed)"
    if not _gone_within(cfg, name, grace):
        how = "killed"
        signal_cells(cfg, st.pid, signal.SIGKILL)
        _gone_within(cfg, name, grace)
    path.unlink(missing_ok=True)
    return how


def _gone_within(cfg: Config, name: str, seconds: float) -> bool:
    """Whether the process of pid file `name` is gone (or a zombie) within `seconds`."""
    deadline = Deadline(seconds)
    while read_pid(cfg, name).alive:
        if deadline.expired:
            return False
        time.sleep(0.05)
    return True


def _wait_gone(cfg: Config, st: ProcStatus, grace: float = GRACE) -> str:
    """Wait for a process that is exiting of itself (it removed its own pid file); SIGKILL after grace."""
    assert st.pid is not None
    pid = st.pid
    ticks = _proc_start_ticks(pid)

    def alive() -> bool:
        return ticks is not None and _proc_start_ticks(pid) == ticks and not _zombie(pid)

    deadline = Deadline(grace)
    while alive() and not deadline.expired:
        time.sleep(0.05)
    if not alive():
        return "stopped"
    why = signal_cells(cfg, pid, signal.SIGKILL)
    return "killed" if why is None else f"not killed: {why}"


def clean_machine_state(cfg: Config, machine_ids: list[str]) -> list[str]:
    """Remove the queues and pty links of these machines (they outlive their processes by design)."""
    from gwc.ipc.mq import remove_queues

    removed = remove_queues(cfg.ipc_prefix, machine_ids)
    for mid in machine_ids:
        pty = cfg.run_dir / f"cmm-{mid}.pty"
        if pty.exists():
            pty.unlink()
            removed.append(str(pty))
    return removed


def stop_cell(cfg: Config, log: logging.Logger, say: Callable[[str], None] = print, database: bool = True) -> None:
    # Lot scripts first, while the servers they clean up through (ls, msched) still run; all told at
    # once, so they clean up side by side. The agent's own first, so that it does not restart them.
    if agent_control.running(cfg):
        agent_control.call(cfg, "stop_lots", say=say)
    lots = [p.stem.replace("-", ":", 1) for p in sorted(cfg.run_dir.glob("lot-*.pid"))] if cfg.run_dir.exists() else []
    told = set()
    for name in lots:
        st = read_pid(cfg, name)
        if st.alive and st.pid is not None and signal_cells(cfg, st.pid, signal.SIGTERM) is None:
            told.add(name)  # what is not the cell's, stop_proc says below

    def stopped(name: str, what: str) -> None:
        if what.startswith(REFUSED):  # a pid file that named what is not the cell's: said in the log too
            log.warning("%s: %s", name, what)
        say(f"{name}: {what}")

    for name in lots:
        what = stop_proc(cfg, name)
        stopped(name, "stopped" if what == "was dead" and name in told else what)  # it went when told
    if agent_control.running(cfg):  # the agent stops its modules in reverse order, then itself
        agent = read_pid(cfg, AGENT.name)
        agent_control.call(cfg, "stop", say=say, exit=True)
        say(f"agent: {_wait_gone(cfg, agent) if agent.pid else stop_proc(cfg, AGENT.name)}")
    for proc in reversed(cell_procs(cfg)):
        what = stop_proc(cfg, proc.name)
        if what != "not running":
            stopped(proc.name, what)
    # Pid files of processes no longer in the configuration (or started by hand) go too.
    if cfg.run_dir.exists():
        for path in cfg.run_dir.glob("*.pid"):
            name = path.stem.replace("-", ":", 1)
            stopped(name, stop_proc(cfg, name))
    for item in clean_machine_state(cfg, [m.id for m in cfg.machines]):
        log.info("removed %s", item)
    if database and cfg.embedded:
        db.cluster_stop(cfg, log)
        say("database: stopped")


def cell_status(cfg: Config) -> tuple[dict[str, Any] | None, list[dict[str, Any]]]:
    """(the agent, or None if none runs; each module's state, pid, uptime, restarts, alive)."""
    try:
        answer = agent_control.call(cfg, "status", timeout=10.0)
    except agent_control.NoAgent:
        rows = []
        for p in cell_procs(cfg):
            st = read_pid(cfg, p.name)
            state = "RUNNING" if st.alive else "STOPPED"
            rows.append({"module": p.name, "state": state, "pid": st.pid if st.alive else None, "since": st.since})
        return None, [{**r, "alive": "yes" if r["state"] == "RUNNING" else "no"} for r in rows]
    rows = [{**r, "alive": "yes" if r["state"] in ("RUNNING", "STARTING") else "no"} for r in answer["modules"]]
    return answer["agent"], rows
