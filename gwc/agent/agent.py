"""The agent: one per host. It starts the host's modules, learns of a death at once, and restarts.

* **Start.** Every module of etc/cell.toml, in its order, each its own process in a session of its
  own (the agent's child). A module is RUNNING once proven ready: a server on the bus (a new
  incarnation) and through its STARTUP conversation, a WC on the bus (its machine then resumes, or
  waits Shutdown for `gwc machine start`), an ME or simulator (off the bus) by writing to the pipe
  the agent gave it ($GWC_READY_FD, as systemd's sd_notify) once it serves its queues or its line.
* **Deaths.** Each process has a pidfd in the event loop; its exit is seen at once. The agent
  broadcasts Module_Died (MOD_DIED) before anything else, so the Machine Server, MSCHED and the lots
  act on it, then restarts the module: at once if it had run `start_secs`, else after a backoff
  (`backoff`, doubling to `backoff_max`). A module that dies `start_retries` times in a row before
  it has run `start_secs` is FATAL: left down, alarm MODULE_FATAL raised; `gwc start` or `gwc
  restart` tries it again.
* **The agent's own death.** The modules do not depend on it (own sessions, own bus members): a
  killed agent leaves them running, unwatched, until an agent runs again (`gwc start`, or the
  host's service manager), which adopts every module its pid file names and finds alive (watched
  by pidfd again, exit status unknown), and starts the rest. SIGTERM to the agent is an orderly stop
  of the host's part of the cell: every module stopped in reverse order, then the agent.
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import functools
import json
import logging
import os
import signal
import socket
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, fields
from typing import Any

from gwc import lothosts as hosting
from gwc.agent.child import Child, Process
from gwc.agent.control import READY_FD, address, peer_of
from gwc.agent.lot_hosts import LotHosting
from gwc.agent.states import LIVE, ProcessState
from gwc.budget import plan
from gwc.cell import cell_procs, hold_startup, lot_proc, pid_file, read_pid, spawn_process, write_pid_file
from gwc.config import Config
from gwc.errors import ConfigError, GwcError, ModuleError
from gwc.hostuser import clear_ambient, lot_user, lot_user_wanted_but_unusable
from gwc.ipc import eventloop
from gwc.ipc.bus import Bus
from gwc.ipc.catalogue import Message, message
from gwc.ipc.names import Conv, Msg
from gwc.lease import EXIT_DEPOSED
from gwc.log import TRACE
from gwc.lot.admission import LotQueue
from gwc.lot.launcher import LotLauncher
from gwc.lot.run import Forked, fork_lot_script
from gwc.module import ask, module_name
from gwc.private import open_lock, secure_var
from gwc.retry import Deadline
from gwc.servers.common import Server

OFF_BUS = ("me", "cmmsim")  # proven ready by staying alive; their WC proves the rest
BLOCKED_SAY_S = 30.0  # s: how often the log says queued lot scripts wait for a place
START_BOOST = 5  # a process starting is scheduled ahead of the cell (niceness this much lower) until ready
# A lot script taken over from a dead host keeps it this long past ready: its resume (record read, leftovers
# cleaned, machines given back) is what production waits for in a failover, while every module reconnects.
TAKEOVER_BOOST_S = 3.0


@dataclass(frozen=True)
class Policy:
    """The restart policy, from cell.toml's [agent] table (docs/operating.md)."""

    start_retries: int = 3  # deaths in a row before start_secs of running: then FATAL
    start_secs: float = 5.0  # a module that ran this long was started well: its next death restarts it at once
    backoff: float = 0.5  # the first pause after a failed start, doubling ...
    backoff_max: float = 8.0  # ... up to this
    start_timeout: float = 30.0  # a module not ready within this is killed (a failed start)
    grace: float = 5.0  # between SIGTERM and SIGKILL when stopping
    # The niceness the agent runs at, and so every process it starts: the cell's beats, restarts and
    # steps come before the host's batch work. Lowering it needs privilege (root, CAP_SYS_NICE); without
    # it the agent says so once and runs as it is. 0: as started.
    nice: int = -5

    @classmethod
    def of(cls, cfg: Config) -> Policy:
        raw = dict(cfg.raw.get("agent", {}))
        known = {f.name: f.type for f in fields(cls)}
        unknown = set(raw) - set(known)
        if unknown:
            raise ConfigError(f"{cfg.path}: [agent] has unknown key(s) {', '.join(sorted(unknown))}")
        for key, value in raw.items():
            if key == "nice" and not (type(value) is int and -20 <= value <= 19):
                raise ConfigError(f"{cfg.path}: [agent] nice = {value!r} is not a whole number from -20 to 19")
            if isinstance(value, bool) or not isinstance(value, (int, float)) or (value < 0 and key != "nice"):
                raise ConfigError(f"{cfg.path}: [agent] {key} = {value!r} is not a number >= 0")
            if known[key] == "int" and not isinstance(value, int):
                raise ConfigError(f"{cfg.path}: [agent] {key} = {value!r} is not a whole number")
        return cls(**raw)


def agent_name(host: str | None = None) -> str:
    """The agent's bus and log name: agent:<host>."""
    return module_name("agent", host or socket.gethostname().split(".")[0])


class Agent(Server):
    """One host's supervisor (see the module docstring)."""

    def __init__(self, cfg: Config, log: logging.Logger, host: str | None = None) -> None:
        self.cfg = cfg
        self.log = log
        self.name = agent_name(host or cfg.host)
        self.policy = Policy.of(cfg)
        self.bus = Bus(self.name, cfg.bus, log)
        self._tasks: set[asyncio.Task[None]] = set()
        self.children = {p.name: Child(p, log) for p in cell_procs(cfg)}
        self.budget = plan(cfg)
        self.queue = LotQueue(cfg.run_dir)  # entities whose scripts wait for a place (_admit)
        self._blocked_said = 0.0  # when the log last said the queue waits for a place
        self._stop = asyncio.Event()
        self._stopping = False
        self.lot_user = lot_user(cfg)  # whom lot scripts run as: None, the agent's user (gwc.hostuser)
        # Scripts of the lot user are forked by a launcher of its (gwc/lot/launcher.py), else exec'd.
        self.launcher = LotLauncher(cfg, self.lot_user, log, self._waited) if self.lot_user else None
        self.hosting: LotHosting | None = None

    async def ask(
        self,
        cls: str,
        first: Message,
        to: str | None,
        timeout: float | None = None,
        *more: Message,
        within: float = 0.0,
    ) -> Message:
        """module.ask() on the agent's bus (Server.raise_alarm asks the Cell Alarm Server through it)."""
        return await ask(self.bus, cls, first, to, timeout, *more, within=within)

    # ----------------------------------------------------------------- the agent's life

    async def run(self) -> int:
        clear_ambient()  # capabilities `gwc start` handed it: for it alone, never for what it execs
        secure_var(self.cfg)
        with os.fdopen(open_lock(self.cfg.run_dir / "agent.lock"), "w") as lock:
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise ModuleError(f"an agent already runs for {self.cfg.var} on this host") from None
            write_pid_file(self.cfg, "agent", os.getpid(), ["gwc", "agent"])
            self._prioritise()
            await self.bus.sign_on()
            server = await asyncio.start_unix_server(self._serve, path=address(self.cfg))
            loop = asyncio.get_running_loop()
            for sig in (signal.SIGTERM, signal.SIGINT):
                loop.add_signal_handler(sig, lambda: self.spawn(self.stop_all(exit_after=True)))
            self.log.info("agent %s (pid %d) supervising %d modules", self.name, os.getpid(), len(self.children))
            self.log.info("lot scripts: %s", self.budget.describe())
            if self.lot_user is not None:
                self.log.info("lot scripts run as user %s (uid %d)", self.lot_user.name, self.lot_user.uid)
            elif why := lot_user_wanted_but_unusable(self.cfg):
                self.log.warning("lot scripts run as the cell's user (uid %d): %s", os.geteuid(), why)
            if self.launcher is not None:
                self.launcher.start()
            self._adopt()
            self.spawn(self._start_all_logged())
            if hosting.hosted(self.cfg):  # lot scripts outlive their host (gwc/agent/lot_hosts.py)
                self.hosting = LotHosting(self)
                self.spawn(self.hosting.run())
            try:
                await self._stop.wait()
            finally:
                server.close()
                if self.launcher is not None:
                    self.launcher.close()
                for t in list(self._tasks):
                    t.cancel()
                await self.bus.close()
                with contextlib.suppress(OSError, ValueError, KeyError):
                    if json.loads(pid_file(self.cfg, "agent").read_text())["pid"] == os.getpid():
                        pid_file(self.cfg, "agent").unlink()
                self.log.info("agent stopped")
        return 0

    def _prioritise(self) -> None:
        """Run at the policy's niceness; the processes the agent starts inherit it."""
        want = self.policy.nice
        try:
            now = os.getpriority(os.PRIO_PROCESS, 0)
            if want != 0 and now != want:
                os.setpriority(os.PRIO_PROCESS, 0, want)
                self.log.info("running at niceness %d (was %d), and so the modules it starts", want, now)
        except OSError as e:  # not privileged: the cell runs as it is
            self.log.warning("cannot run at niceness %d (%s): the modules run at the host's default", want, e)

    def _boost(self, pid: int | None, boost: int) -> None:
        """Every thread of the process at the agent's niceness minus `boost` (Linux's setpriority
        changes one thread: a process that started threads needs each set). Best effort: without
        privilege, or with the process gone, nothing changes."""
        if pid is None or self.policy.nice == 0:
            return
        nice = max(-20, self.policy.nice - boost)
        try:
            tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
        except OSError:
            tids = [pid]
        for tid in tids:
            with contextlib.suppress(OSError):
                os.setpriority(os.PRIO_PROCESS, tid, nice)

    def _waited(self) -> set[int]:
        """The processes this agent waits for itself (its launcher's sweep leaves them be)."""
        pids = {c.pid for c in self.children.values() if c.pid is not None}
        return pids | (self.hosting.pids() if self.hosting is not None else set())

    def _adopt(self) -> None:
        """Modules (and lot scripts) an earlier agent started and left running are watched again, not
        started twice."""
        for path in sorted(self.cfg.run_dir.glob("lot-*.pid")):
            entity = path.stem.partition("-")[2]
            if entity.isdigit():
                self.children.setdefault(f"lot:{entity}", Child(lot_proc(int(entity)), self.log))
        for child in self.children.values():
            st = read_pid(self.cfg, child.name)
            if not st.alive or st.pid is None:
                continue
            pid = st.pid
            ours = child.attach(pid, None, self._exited, still_ours=functools.partial(_names, self.cfg, child, pid))
            if ours:
                child.change_state(ProcessState.STARTING, "adopted: left running by an earlier agent")
                child.ready = asyncio.get_running_loop().create_task(self._probe(child, None))

    async def _start_all_logged(self) -> None:
        try:
            await self.start_some(list(self.children), self.log.info)
        except GwcError as e:
            self.log.error("starting the host's modules: %s", e)
        self._admit()  # the scripts an earlier agent left queued

    # ----------------------------------------------------------------- starting

    def _spawn(self, child: Child, why: str) -> None:
        """A new process for the module: STARTING, and its readiness probe."""
        if child.retry is not None:
            child.retry.cancel()
            child.retry = None
        old = self.bus.peers().get(child.name)
        ready_r, ready_w = os.pipe() if self._ready_by_pipe(child) else (None, None)
        try:
            env = {READY_FD: str(ready_w)} if ready_w is not None else None
            fds = (ready_w,) if ready_w is not None else ()
            popen: Process
            if child.proc.kind == "lot" and self.launcher is not None:  # not our fork: it would hold our keys
                popen = self.launcher.script(int(child.proc.machine or 0))
            elif child.proc.kind == "lot":  # a fork of the agent, which imported what a lot script needs
                popen = fork_lot_script(self.cfg, int(child.proc.machine or 0))
            else:
                popen = spawn_process(self.cfg, child.proc, env, pass_fds=fds)
        except OSError:
            if ready_r is not None:
                os.close(ready_r)
            raise
        finally:
            if ready_w is not None:
                os.close(ready_w)
        child.attach(popen.pid, popen, self._exited)
        self._boost(popen.pid, START_BOOST)  # until it is ready: the 3 s a restart has are mostly its CPU
        child.change_state(ProcessState.STARTING, why)
        probe = self._probe(child, old.inc if old else None, ready_r)
        child.ready = asyncio.get_running_loop().create_task(probe)
        if ready_r is not None:  # closed however the probe ends, even cancelled before its first step
            fd = ready_r
            child.ready.add_done_callback(lambda _t: os.close(fd))

    async def _probe(self, child: Child, old_inc: int | None, ready_fd: int | None = None) -> None:
        """Prove the new process ready (RUNNING), or kill it: a failed start, counted when it dies.
        An adopted off-bus process (no pipe) ran before: it is taken as ready."""
        pid = child.pid
        kind = child.proc.kind
        how = "ready"
        try:
            async with asyncio.timeout(self.policy.start_timeout):
                if self._ready_by_pipe(child):
                    if ready_fd is not None:
                        await _read_ready(ready_fd)
                else:
                    while True:
                        peer = self.bus.peers().get(child.name)
                        if peer is not None and peer.inc != old_inc:
                            break
                        await asyncio.sleep(0.02)
                    how = "on the bus"
                    if kind not in ("wc", "lot"):
                        how = await hold_startup(self.bus, child.name, timeout=self.policy.start_timeout)
        except TimeoutError:
            why = f"not ready within {self.policy.start_timeout:g}s"
        except GwcError as e:
            why = str(e)
        else:
            if child.pid == pid and child.state == ProcessState.STARTING:
                left = max(0.0, child.boost_until - time.monotonic())  # a takeover's boost lasts a while
                asyncio.get_running_loop().call_later(left, self._unboost, child, pid)
                child.change_state(ProcessState.RUNNING, how)
            return
        if child.pid == pid and child.state == ProcessState.STARTING:
            self.log.error("%s (pid %s): %s: killing it", child.name, pid, why)
            child.last_exit = why
            child.signal_group(signal.SIGKILL)

    def _unboost(self, child: Child, pid: int | None) -> None:
        """A start's boost ends (past TAKEOVER_BOOST_S for a takeover), if its process still runs."""
        if child.pid == pid and child.state in LIVE:
            self._boost(pid, 0)

    def _ready_by_pipe(self, child: Child) -> bool:
        """Whether the process proves itself ready through the pipe: one off the bus, and an instance
        of a redundant module, which is off the bus while it stands by (gwc/lease.py) and starts
        itself when it becomes the active one."""
        return child.proc.kind in OFF_BUS or (child.proc.machine is None and self.cfg.leased(child.proc.kind))

    async def bring_up(self, child: Child, say: Callable[[str], None]) -> None:
        """Start a module that is not running (an operator's start: FATAL and BACKOFF try again at once)
        and wait until it is RUNNING or FATAL."""
        if child.state == ProcessState.STOPPING:
            await self._wait(child, (ProcessState.STOPPED,), self.policy.grace * 3)
        if child.state in (ProcessState.STOPPED, ProcessState.FATAL, ProcessState.BACKOFF):
            child.fails = 0
            self._spawn(child, "started")
            say(f"{child.name}: spawned (pid {child.pid})")
        elif child.state == ProcessState.RUNNING:
            say(f"{child.name}: already running (pid {child.pid})")
            return
        await self._wait(
            child,
            (ProcessState.RUNNING, ProcessState.FATAL),
            self.policy.start_timeout * (self.policy.start_retries + 1),
        )
        if child.state == ProcessState.FATAL:
            raise ModuleError(f"{child.name} is FATAL: {child.last_exit} (see {self.cfg.log_dir})")
        say(f"{child.name}: {child.state} (pid {child.pid})")

    def spawn_lots(self, entities: list[int]) -> dict[str, int | None]:
        """Queue lot scripts (`gwc order new`, through gwc.lot.run.spawn_lot_script) and start as many as
        the budget has places for (_admit): watched and restarted as modules are while they run,
        forgotten once they end of themselves. A script running already is left as it is. Returns
        entity -> pid, None for a script that waits in the queue."""
        for entity in entities:
            child = self.children.get(lot_proc(entity).name)
            if child is None or child.state not in LIVE:
                self.queue.add(entity)
        self._admit()
        pids: dict[str, int | None] = {}
        for entity in entities:
            child = self.children.get(lot_proc(entity).name)
            pids[str(entity)] = child.pid if child is not None and child.state in LIVE else None
        return pids

    def lot_places(self) -> int:
        """Lot scripts the budget lets start now: its most at once, less those running or queued."""
        return self.budget.running - self._lots_running() - len(self.queue.pending())

    def adopt_lot(self, entity: int, process: Forked) -> bool:
        """Make a lot script started ahead of its claim (gwc/agent/lot_hosts.py) the entity's, as _spawn
        makes a new one: pid file, watched, STARTING until it is on the bus. False (the caller lets it
        go) if the entity's script runs already, the budget is full, or the process is gone."""
        proc = lot_proc(entity)
        child = self.children.get(proc.name) or Child(proc, self.log)
        if self._stopping or child.state in LIVE or self._lots_running() >= self.budget.running:
            return False
        old = self.bus.peers().get(child.name)
        if not child.attach(process.pid, process, self._exited):
            return False
        self.children[proc.name] = child
        write_pid_file(self.cfg, proc.name, process.pid, proc.argv)
        child.fails = 0
        self.queue.remove(entity)
        self._boost(process.pid, START_BOOST)
        child.boost_until = time.monotonic() + TAKEOVER_BOOST_S
        child.change_state(ProcessState.STARTING, "taken over: started ahead")
        child.ready = asyncio.get_running_loop().create_task(self._probe(child, old.inc if old else None))
        return True

    def _lots_running(self) -> int:
        """Lot scripts holding a place: running, starting, or waiting to be restarted (BACKOFF)."""
        return sum(
            1 for c in self.children.values() if c.proc.kind == "lot" and c.state in (*LIVE, ProcessState.BACKOFF)
        )

    def _admit(self) -> None:
        """Start queued lot scripts, oldest first, while fewer than the budget's run. A script that cannot be
        started is logged and left queued (the next script's end tries again)."""
        if self._stopping:
            return
        running = self._lots_running()
        pending = self.queue.pending()
        for entity in pending:
            if running >= self.budget.running:
                now = time.monotonic()
                if now - self._blocked_said >= BLOCKED_SAY_S:
                    self._blocked_said = now
                    self.log.info(
                        "lot scripts: %d running (the most at once), %d queued: the next starts when one ends",
                        running,
                        len(pending) - pending.index(entity),
                    )
                return
            proc = lot_proc(entity)
            child = self.children.setdefault(proc.name, Child(proc, self.log))
            if child.state in LIVE:  # started by an earlier `gwc order new` or adopted
                self.queue.remove(entity)
                continue
            child.fails = 0
            try:
                self._spawn(child, "started")
            except OSError as e:
                self.children.pop(proc.name, None)
                self.log.error("could not start the lot script of entity %d (left queued): %s", entity, e)
                return
            self.queue.remove(entity)
            running += 1

    async def start_some(self, names: list[str], say: Callable[[str], None]) -> None:
        """Bring modules up in cell.toml's order, each RUNNING before the next; every failure is reported."""
        failed = []
        for name in names:
            child = self.children.get(name)
            if child is None:  # gone meanwhile: a lot script that ended, or that another host took over
                continue
            try:
                await self.bring_up(child, say)
            except GwcError as e:
                say(f"{name}: {e}")
                failed.append(str(e))
        if failed:
            raise ModuleError("; ".join(failed))

    # ----------------------------------------------------------------- deaths

    def _exited(self, child: Child) -> None:
        """pidfd callback: the process is gone. Announce it, then restart, back off, or give up."""
        pid = child.pid
        process = child.popen
        how = child.reap()
        if child.ready is not None:
            child.ready.cancel()
            child.ready = None
        named = False  # whether its pid file still names it: a lot script removes its own when it ends
        with contextlib.suppress(OSError, ValueError, KeyError):
            if named := json.loads(pid_file(self.cfg, child.name).read_text())["pid"] == pid:
                pid_file(self.cfg, child.name).unlink()
        lot = child.proc.kind == "lot"
        if child.state == ProcessState.STOPPING or (lot and not _killed(child.last_code, named)):
            if isinstance(process, Forked) and process.cpu_s is not None:
                how += f", {process.cpu_s * 1000:.0f} ms of CPU"
            child.change_state(
                ProcessState.STOPPED, how if child.state == ProcessState.STOPPING else f"{how}: its work is done"
            )
            if lot:
                self.children.pop(child.name, None)
                self._admit()  # its place goes to the next queued script
            return
        if child.state == ProcessState.RUNNING and time.monotonic() - child.running_at >= self.policy.start_secs:
            child.fails = 0
        deposed = child.last_code == EXIT_DEPOSED  # lost its lease: back at once as a standby, not a failure
        child.fails += 0 if deposed else 1
        delay: float | None = None
        if deposed:
            delay = 0.0
            child.change_state(ProcessState.BACKOFF, f"{how}: deposed; again as a standby")
        elif child.fails >= self.policy.start_retries:
            child.change_state(ProcessState.FATAL, f"{how}; {child.fails} failed starts in a row")
            text = f"{child.name} failed {child.fails} times in a row ({how}): left down"
            self.spawn(self.raise_alarm("MODULE_FATAL", text, child.proc.machine))
            if lot:
                self._admit()
        else:
            pause = self.policy.backoff * 2 ** (child.fails - 2)
            delay = 0.0 if child.fails == 1 else min(pause, self.policy.backoff_max)
            child.change_state(ProcessState.BACKOFF, f"{how}; restart in {delay:g}s")
        # The announcement's task is scheduled before the restart's timer: it goes out first.
        self.spawn(self._announce(child, pid, how, delay))
        if delay is not None:
            child.retry = asyncio.get_running_loop().call_later(delay, self._restart, child)

    def _restart(self, child: Child) -> None:
        child.retry = None
        if child.state != ProcessState.BACKOFF or self._stopping:
            return
        child.restarts += 1
        try:
            self._spawn(child, f"restart {child.restarts}")
        except OSError as e:  # cannot even fork/exec: counts as a failed start
            self.log.error("%s: could not spawn: %s", child.name, e)
            child.fails += 1
            child.change_state(ProcessState.FATAL, f"spawn failed: {e}")

    async def _announce(self, child: Child, pid: int | None, how: str, delay: float | None) -> None:
        try:
            await self.broadcast(
                Conv.MOD_DIED,
                message(
                    Msg.MODULE_DIED,
                    module=child.name,
                    host=self.name,
                    pid=pid,
                    how=how,
                    state=child.state.value,
                    restarts=child.restarts,
                    restart_in=delay,
                ),
            )
        except GwcError as e:
            self.log.error("could not announce the death of %s: %s", child.name, e)

    # ----------------------------------------------------------------- stopping

    async def stop_child(self, child: Child, say: Callable[[str], None]) -> None:
        """SIGTERM, `grace`, SIGKILL: STOPPED, and not restarted."""
        if child.retry is not None:
            child.retry.cancel()
            child.retry = None
        if child.state in (ProcessState.BACKOFF, ProcessState.FATAL):
            child.change_state(ProcessState.STOPPED, "stopped")
        if child.state == ProcessState.STOPPED:
            return
        if child.state != ProcessState.STOPPING:
            child.change_state(ProcessState.STOPPING, "stop")
            if child.ready is not None:
                child.ready.cancel()
            child.signal_group(signal.SIGTERM)
        how = "stopped"
        if not await self._wait(child, (ProcessState.STOPPED,), self.policy.grace):
            how = "killed"
            child.signal_group(signal.SIGKILL)
            await self._wait(child, (ProcessState.STOPPED,), self.policy.grace)
        say(f"{child.name}: {how}")

    async def stop_all(self, exit_after: bool, say: Callable[[str], None] | None = None) -> None:
        """Every module in reverse order; then, if asked, the agent itself."""
        self._stopping = exit_after or self._stopping
        await self.stop_lots(say or self.log.info)
        for child in reversed(list(self.children.values())):
            await self.stop_child(child, say or self.log.info)
        if exit_after:
            self._stop.set()

    async def stop_lots(self, say: Callable[[str], None]) -> None:
        """Every lot script, side by side (each fails its entity cleanly on SIGTERM), before the servers
        they clean up through stop."""
        lots = [c for c in self.children.values() if c.proc.kind == "lot"]
        await asyncio.gather(*(self.stop_child(c, say) for c in lots))

    async def _wait(self, child: Child, states: Iterable[ProcessState], timeout: float) -> bool:
        deadline = Deadline(timeout)
        wanted = tuple(states)
        while child.state not in wanted:
            left = deadline.left()
            if left <= 0:
                return False
            child.changed.clear()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(child.changed.wait(), left)
        return True

    # ----------------------------------------------------------------- the control socket

    def _pick(self, names: list[str] | None) -> list[Child]:
        if not names:
            return list(self.children.values())
        unknown = [n for n in names if n not in self.children]
        if unknown:
            known = ", ".join(self.children)
            raise ModuleError(f"no module {', '.join(unknown)} on this host's agent (known: {known})")
        return [c for c in self.children.values() if c.name in names]  # cell.toml's order

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        def say(text: str) -> None:
            writer.write(json.dumps({"say": text}).encode() + b"\n")

        answer: dict[str, Any] = {}
        peer = peer_of(writer.get_extra_info("socket"))
        who = f"uid {peer.uid} (pid {peer.pid})"
        try:
            if not peer.allowed:  # no parser sees what it sends: taken off the socket (briefly), unread
                self.log.warning("control: refused a connection from %s: not the cell's user nor root", who)
                with contextlib.suppress(TimeoutError, ValueError, OSError):
                    await asyncio.wait_for(reader.readline(), 1.0)  # else the close could reset its answer
                raise ModuleError(f"not allowed: the agent takes commands from uid {os.geteuid()} and root only")
            req = json.loads(await reader.readline())
            if not isinstance(req, dict):
                raise ValueError("not a JSON object")
            cmd = req.get("cmd")
            names = req.get("names")
            if names is not None and not (isinstance(names, list) and all(isinstance(n, str) for n in names)):
                raise ValueError("names must be a list of module names")
            quiet = cmd == "ping"  # asked by most `gwc` commands (is an agent there?): changes and tells nothing
            what = " ".join([str(cmd), *(names or [])])[:200]
            self.log.log(TRACE if quiet else logging.INFO, "control: %s from %s", what, who)
            if cmd == "ping":
                pass
            elif cmd == "status":
                answer["agent"] = {"name": self.name, "pid": os.getpid()}
                answer["modules"] = [c.row() for c in self.children.values()]
            elif cmd == "lots":
                entities = req.get("entities")
                if not (isinstance(entities, list) and all(type(e) is int and e > 0 for e in entities)):
                    raise ValueError("entities must be a list of entity ids")
                answer["pids"] = self.spawn_lots(entities)
            elif cmd == "stop_lots":
                await self.stop_lots(say)
            elif cmd == "start":
                await self.start_some([c.name for c in self._pick(names)], say)
            elif cmd == "stop":
                if names:
                    for child in reversed(self._pick(names)):
                        await self.stop_child(child, say)
                else:
                    await self.stop_all(exit_after=bool(req.get("exit")), say=say)
            elif cmd == "restart":
                picked = self._pick(names)
                if not names:
                    raise ModuleError("restart: name the module(s) to restart")
                for child in reversed(picked):
                    await self.stop_child(child, say)
                await self.start_some([c.name for c in picked], say)
            else:
                raise ModuleError(
                    f"unknown agent command {cmd!r} (ping, status, start, stop, restart, lots, stop_lots)"
                )
            answer.update(done=True, ok=True)
        except (ValueError, UnicodeDecodeError) as e:
            self.log.warning("control: bad request from %s: %s", who, e)
            answer = {"done": True, "ok": False, "error": f"bad request: {e}"}
        except GwcError as e:
            answer = {"done": True, "ok": False, "error": str(e)}
        try:
            writer.write(json.dumps(answer).encode() + b"\n")
            await writer.drain()
            writer.close()
        except OSError as e:  # the asker went away: nothing to tell it
            self.log.info("control: %s", e)


async def _read_ready(fd: int) -> None:
    """Wait for the module's byte on its readiness pipe; EOF means it ended first."""
    loop = asyncio.get_running_loop()
    got: asyncio.Future[bytes] = loop.create_future()

    def take() -> None:
        if not got.done():
            got.set_result(os.read(fd, 1))

    loop.add_reader(fd, take)
    try:
        if not await got:
            raise ModuleError("ended before it was ready")
    finally:
        loop.remove_reader(fd)


def _killed(code: int | None, named: bool) -> bool:
    """Whether a lot script died rather than ended: killed by a signal other than a request to stop
    (SIGTERM, SIGINT: it fails its entity cleanly, or was stopped before it could); when its exit status is
    unknown (adopted), whether its pid file still names it (a script removes its own when it ends)."""
    if code is None:
        return named
    return code < 0 and -code not in (signal.SIGTERM, signal.SIGINT)


def _names(cfg: Config, child: Child, pid: int) -> bool:
    st = read_pid(cfg, child.name)
    return st.alive and st.pid == pid


def run_agent(cfg: Config, log: logging.Logger, host: str | None = None) -> int:
    """`gwc agent`: supervise this host's modules until SIGTERM (which stops them) or `gwc stop`."""
    return eventloop.run(Agent(cfg, log, host).run())


__all__ = ["Agent", "Policy", "agent_name", "run_agent"]
