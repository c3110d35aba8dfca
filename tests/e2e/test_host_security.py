"""Least privilege on the host (issue 40): an unprivileged local account, made by the test, attacks a
cell started with `gwc start` (as root, as CI runs it) through what the host shares: var/ and its pid
files, symlinks and locks, the WC<->ME queues, and the agent's control socket. Each is refused or
harmless, with a clear log line, and the cell goes on (`gwc check` clean)."""

from __future__ import annotations

import fcntl
import json
import os
import pwd
import shutil
import signal
import socket
import subprocess
import tempfile
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import posix_ipc
import psycopg
import pytest

from gwc.agent import control as agent_control
from gwc.cell import pid_file
from gwc.config import Config
from gwc.ipc.mq import LAYOUT_SIZE, queue_names
from gwc.log import log_file_name
from tests.e2e.test_cell import gwc
from tests.harness import wait_for, write_cell_config

pytestmark = [
    pytest.mark.e2e,
    pytest.mark.skipif(os.geteuid() != 0, reason="makes a local account (useradd) and acts as it"),
]


class LocalUser:
    """An unprivileged account of the host, made for the test and removed after it, even on failure."""

    def __init__(self) -> None:
        self.name = f"gwct{uuid.uuid4().hex[:8]}"
        subprocess.run(["useradd", "--no-create-home", "--shell", "/bin/sh", self.name], check=True)
        self.uid, self.gid = pwd.getpwnam(self.name).pw_uid, pwd.getpwnam(self.name).pw_gid
        self.procs: list[subprocess.Popen[bytes]] = []

    def run(self, fn: Callable[..., Any], *args: Any) -> Any:
        """fn(*args) in a child of this process that has become this user (os.setuid); its JSON result."""
        r, w = os.pipe()
        pid = os.fork()
        if pid == 0:  # the child: drop to the user, never return into pytest
            code = 1
            try:
                os.close(r)
                os.setgroups([])
                os.setgid(self.gid)
                os.setuid(self.uid)
                os.write(w, json.dumps(fn(*args)).encode())
                code = 0
            finally:
                os._exit(code)
        os.close(w)
        with os.fdopen(r) as f:
            out = f.read()
        _, status = os.waitpid(pid, 0)
        assert os.waitstatus_to_exitcode(status) == 0, f"{fn.__name__} failed as {self.name}"
        return json.loads(out)

    def sleeper(self) -> subprocess.Popen[bytes]:
        """A process of this user's (a planted pid file will name it)."""
        p = subprocess.Popen(["sleep", "300"], user=self.uid, group=self.gid, extra_groups=[], start_new_session=True)
        self.procs.append(p)
        return p

    def remove(self) -> None:
        for p in self.procs:
            p.kill()
            p.wait()
        subprocess.run(["userdel", self.name], check=False, capture_output=True)


@pytest.fixture
def local_user() -> Iterator[LocalUser]:
    user = LocalUser()
    try:
        yield user
    finally:
        user.remove()


@pytest.fixture
def reachable_var(database_url: str) -> Iterator[tuple[Config, dict[str, str]]]:
    """A cell whose var/ sits where any user may walk up to it (/tmp/x, 0755): only var/'s own modes
    keep the local user out, not a private pytest folder above it."""
    base = Path(tempfile.mkdtemp(prefix="gwc-host-"))
    base.chmod(0o755)
    cfg = write_cell_config(
        base / "var",
        database_url,
        machines=[{"id": m, "kind": "dummy", "run_time": 0.1} for m in ("wc1", "wc2")],
    )
    env = dict(os.environ, GWC_CONFIG=str(cfg.path), GWC_VAR=str(cfg.var), GWC_DATABASE_URL=database_url)
    try:
        yield cfg, env
    finally:
        gwc(env, "stop")
        shutil.rmtree(base, ignore_errors=True)


def squat(*names: str) -> str:
    for name in names:
        posix_ipc.MessageQueue(
            name, posix_ipc.O_CREX, mode=0o666, max_messages=10, max_message_size=LAYOUT_SIZE
        ).close()
    return "made"


def count(*names: str) -> list[int]:
    return [posix_ipc.MessageQueue(n).current_messages for n in names]


def try_files(var: str, run: str) -> dict[str, str]:
    tried = {}

    def attempt(what: str, fn: Callable[[], Any]) -> None:
        try:
            fn()
            tried[what] = "done"
        except OSError as e:
            tried[what] = str(e.strerror)

    attempt("list var", lambda: os.listdir(var))
    attempt("list run", lambda: os.listdir(run))
    attempt("plant a pid file", lambda: Path(run, "ms.pid").write_text('{"pid": 1}'))
    attempt("plant a symlink", lambda: os.symlink("/etc/passwd", os.path.join(run, "msched.pid")))
    for lock in ("agent.lock", "pg.lock"):
        attempt(f"hold {lock}", lambda: fcntl.flock(open(os.path.join(run, lock)), fcntl.LOCK_EX | fcntl.LOCK_NB))  # noqa: B023, SIM115
    attempt("read a log", lambda: Path(var, "log", "ms.log").read_text())
    return tried


def call_agent(address: str, cmd: str) -> dict[str, Any]:
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(10)
        s.connect(address)
        s.sendall(json.dumps({"cmd": cmd}).encode() + b"\n")
        return dict(json.loads(s.makefile().readline()))


def log_text(cfg: Config, name: str) -> str:
    try:
        return (cfg.log_dir / log_file_name(name)).read_text(errors="replace")
    except OSError:
        return ""


def status(cfg: Config) -> dict[str, dict[str, Any]]:
    """The agent's rows, asked in this process (as root): a `gwc status` process costs seconds."""
    return {r["module"]: r for r in agent_control.call(cfg, "status")["modules"]}


def test_a_local_user_gets_nothing_the_cell_did_not_give_it(
    reachable_var: tuple[Config, dict[str, str]], local_user: LocalUser
) -> None:
    cfg, env = reachable_var
    squatted = queue_names(cfg.ipc_prefix, "wc2")
    assert local_user.run(squat, *squatted) == "made"  # before the cell starts: the queues are the user's
    started = gwc(env, "start")
    rows = status(cfg)
    assert rows["wc:wc1"]["state"] == "RUNNING" and rows["msched"]["state"] == "RUNNING", started.stdout

    # The squatted queues: refused, never used (nothing written to them), said in the log and an alarm.
    wait_for(lambda: "not the cell's" in log_text(cfg, "wc:wc2"), 20, "wc2's WC to refuse the user's queue")
    assert "not the cell's" in log_text(cfg, "me:wc2")
    assert local_user.run(count, *squatted) == [0, 0]
    with psycopg.connect(env["GWC_DATABASE_URL"]) as conn:
        alarms = conn.execute("SELECT alarm_id, alarm_text FROM alarms WHERE machine_id = 'wc2'").fetchall()
    assert any(a == "IPC_FOREIGN" and "not the cell's" in (text or "") for a, text in alarms), alarms

    # var/ and var/run: nothing to list, plant, link or lock; no log to read.
    for d in (cfg.var, cfg.run_dir):
        assert os.stat(d).st_mode & 0o777 == 0o700 and os.stat(d).st_mode & 0o1000 == 0
    tried = local_user.run(try_files, str(cfg.var), str(cfg.run_dir))
    assert set(tried.values()) == {"Permission denied"}, tried

    # The agent's socket (abstract: any local user can connect): refused, logged with the uid, not obeyed.
    for cmd in ("stop", "lots", "status"):
        answer = local_user.run(call_agent, agent_control.address(cfg), cmd)
        assert answer["ok"] is False and "not allowed" in answer["error"], answer
    agent_log = log_text(cfg, f"agent:{os.uname().nodename.split('.')[0]}")
    assert agent_log.count(f"refused a connection from uid {local_user.uid}") == 3
    assert "control: start from uid 0" in agent_log and "control: status from uid 0" in agent_log  # root's
    assert all(status(cfg)[m]["state"] == "RUNNING" for m in ("msched", "ms", "ls", "wc:wc1", "me:wc1"))

    # Defence in depth, as if a pid file and a link had got there (an older var/run was 1777): a pid
    # file naming another user's process, one naming pid 1, and a link where msched's pid file goes.
    theirs = local_user.sleeper()
    victim = cfg.var.parent / "victim"
    victim.write_text("not the cell's\n")
    for name, pid in (("theirs", theirs.pid), ("init", 1)):
        ticks = int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19])
        pid_file(cfg, name).write_text(json.dumps({"pid": pid, "ticks": ticks}))
    msched = status(cfg)["msched"]["pid"]
    pid_file(cfg, "msched").unlink()
    pid_file(cfg, "msched").symlink_to(victim)
    os.kill(msched, signal.SIGKILL)  # the agent restarts it and writes its pid file anew
    wait_for(lambda: status(cfg)["msched"]["pid"] not in (None, msched), 20, "msched to be restarted")
    assert victim.read_text() == "not the cell's\n" and not pid_file(cfg, "msched").is_symlink()

    checked = gwc(env, "check")
    assert checked.returncode == 0, checked.stdout + checked.stderr
    stopped = gwc(env, "stop")
    assert stopped.returncode == 0, stopped.stderr
    assert "theirs: refused: not signalled" in stopped.stdout and "init: refused" in stopped.stdout, stopped.stdout
    assert theirs.poll() is None, "gwc stop signalled a process that is not the cell's"
