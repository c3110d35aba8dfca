"""Who runs as whom (issue 40): a cell started with `gwc start` as root runs every long-lived process as
the cell's user `gwc` (its agent, modules, database), holding no privilege but the agent's few
capabilities; its lot scripts run as `gwc-lot`, exec'd, with the lot key alone: they cannot read
cell.key nor write outside their own files, and the chess order is still made. One cell (embedded
database, shipped-like configuration naming its users) for both tests; bin/setup makes the users."""

from __future__ import annotations

import contextlib
import json
import os
import pwd
import re
import shutil
import signal
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import psycopg
import pytest

from gwc import db
from gwc.config import PROJECT_ROOT, Config
from gwc.hostuser import AGENT_CAPS, CELL_USER, LOT_USER
from gwc.soak.private_config import private_bus, write_config
from tests.conftest import TEST_PG_SETTINGS
from tests.e2e.lotkit import default_machines
from tests.e2e.test_cell import gwc
from tests.harness import SERVERS, wait_for
from tests.leaks import unmarked


def _users() -> tuple[pwd.struct_passwd, pwd.struct_passwd] | None:
    try:
        return pwd.getpwnam(CELL_USER), pwd.getpwnam(LOT_USER)
    except KeyError:
        return None


def _gwc_can_run_this_checkout() -> bool:
    if os.geteuid() != 0 or _users() is None:
        return False
    probe = [shutil.which("runuser") or "/usr/sbin/runuser", "-u", CELL_USER, "--", sys.executable, "-c", "import gwc"]
    return subprocess.run(probe, cwd="/", capture_output=True, timeout=60).returncode == 0


pytestmark = [
    pytest.mark.e2e,
    pytest.mark.skipif(os.geteuid() != 0, reason="starts the cell as root"),
    pytest.mark.skipif(_users() is None, reason="the users gwc and gwc-lot: run bin/setup as root"),
    pytest.mark.skipif(
        not _gwc_can_run_this_checkout(), reason="user gwc cannot run this checkout's Python (bin/setup says why)"
    ),
]

# A lot script that tries what a hostile one would, says what happened in its log, then does its lot.
PROBE = '''"""Try the cell's secrets and files; then a lot of nothing."""

import json
import os
from pathlib import Path

from gwc.lot import OperationEntity


def attempt(fn):
    try:
        fn()
        return "done"
    except OSError as e:
        return e.strerror


def main(entity: OperationEntity) -> None:
    var = Path(os.environ["GWC_VAR"])
    tried = {
        "read cell.key": attempt(lambda: (var / "secrets" / "cell.key").read_bytes()),
        "read lot.key": attempt(lambda: (var / "secrets" / "lot.key").read_bytes()),
        "list var/secrets": attempt(lambda: os.listdir(var / "secrets")),
        "write a module's log": attempt(lambda: open(var / "log" / "ms.log", "a").write("forged")),
        "make a log": attempt(lambda: (var / "log" / "ms-forged.log").write_text("x")),
        "make a pid file": attempt(lambda: (var / "run" / "ms.pid").write_text("1")),
        "list var/run": attempt(lambda: os.listdir(var / "run")),
        "make a file in var/": attempt(lambda: (var / "planted").write_text("x")),
        "write its own log": attempt(lambda: entity.log.info("probe: writing my own log")),
        "write the configuration": attempt(lambda: open(os.environ["GWC_CONFIG"], "a").write("#")),
    }
    entity.log.info("probe: %s", json.dumps({"uid": os.getuid(), "gid": os.getgid(), "groups": os.getgroups(),
                                              "tried": tried}))
    entity.wait_for_import()
    entity.lot_completed("PASS")
    entity.wait_for_export()
'''


@dataclass
class RootCell:
    cfg: Config
    env: dict[str, str]
    base: Path


@pytest.fixture(scope="module")
def root_cell() -> Iterator[RootCell]:
    """A cell of its own users, started by root with `gwc start`, its var/ where `gwc` may walk to it."""
    base = Path(tempfile.mkdtemp(prefix="gwc-user-", dir="/var/tmp"))
    base.chmod(0o755)
    cfg = write_config(
        base / "etc" / "cell.toml",
        {
            "cell": {"name": "users", "var": str(base / "var"), "user": CELL_USER},
            "bus": private_bus(peer_timeout=1.5, heartbeat=0.2),
            "database": {"settings": TEST_PG_SETTINGS},
            "log": {"level": "note"},
            "lots": {"user": LOT_USER},
            "module": [{"name": m} for m in SERVERS],
            "machine": default_machines(),
        },
    )
    env = {k: v for k, v in os.environ.items() if k != "GWC_DATABASE_URL"}
    env.update(GWC_CONFIG=str(cfg.path), GWC_VAR=str(cfg.var), PYTHONUNBUFFERED="1")
    cell = RootCell(cfg, env, base)
    try:
        with unmarked():  # the cell outlives the first test (it is the module's)
            started = gwc(env, "start", timeout=180)
        assert started.returncode == 0, started.stdout + started.stderr
        yield cell
    finally:
        gwc(env, "stop", timeout=120)
        left = cell_processes(cfg)  # unmarked, so the leak check would not see them: looked for here
        for pid in left:
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
        shutil.rmtree(base, ignore_errors=True)
        assert not left, f"`gwc stop` left {left}"


def ids(pid: int) -> dict[str, Any]:
    """A process's real/effective/saved uids and gids, its groups and effective capabilities (/proc)."""
    status = dict(line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines())
    return {
        "uids": {int(u) for u in status["Uid"].split()[:3]},
        "gids": {int(g) for g in status["Gid"].split()[:3]},
        "caps": int(status["CapEff"], 16),
        "ambient": int(status.get("CapAmb", "0"), 16),
    }


def cell_processes(cfg: Config) -> dict[int, str]:
    """Every process of this cell: those with its var/ in their environment or command line, and the
    embedded cluster's postmaster and all its children."""
    var = str(cfg.var).encode()
    try:
        postmaster = int((cfg.pg_dir / "postmaster.pid").read_text().split("\n", 1)[0])
    except (OSError, ValueError):
        postmaster = -1  # stopped
    found = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit() or int(d.name) == os.getpid():
            continue
        try:
            env = (d / "environ").read_bytes()
            cmd = (d / "cmdline").read_bytes()
            ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError):
            continue
        if b"GWC_VAR=" + var in env.split(b"\0") or var in cmd or int(d.name) == postmaster or ppid == postmaster:
            found[int(d.name)] = cmd.replace(b"\0", b" ").decode(errors="replace").strip()
    return found


def test_the_cell_started_as_root_runs_every_long_lived_process_as_its_user(root_cell: RootCell) -> None:
    cfg = root_cell.cfg
    gwc_user, lot_user = _users()  # type: ignore[misc]
    procs = cell_processes(cfg)
    kinds = {"agent": 0, "modules": 0, "postgres": 0, "launcher": 0}
    agent = int(json.loads((cfg.run_dir / "agent.pid").read_text())["pid"])
    for pid, cmd in procs.items():
        if "gwc.lot.launcher" in cmd:  # the lot user's, which forks the lot scripts: the other test's
            kinds["launcher"] += 1
            continue
        seen = ids(pid)
        assert seen["uids"] == {gwc_user.pw_uid}, f"{cmd} (pid {pid}) runs as {seen}"
        assert seen["gids"] == {gwc_user.pw_gid}, f"{cmd} (pid {pid}) runs as {seen}"
        assert seen["ambient"] == 0, f"{cmd} would pass capabilities on: {seen}"
        if pid == agent:  # the agent's few: to start lot scripts as their user and stop them
            assert seen["caps"] == sum(1 << c for c in AGENT_CAPS), f"the agent holds {seen['caps']:x}"
            kinds["agent"] += 1
        else:
            assert seen["caps"] == 0, f"{cmd} (pid {pid}) holds capabilities {seen['caps']:x}"
            kinds["postgres" if "postgres" in cmd else "modules"] += 1
    # the six servers and three machines' WC and ME (and the CMM simulator); the cluster's processes
    assert kinds["agent"] == 1 and kinds["modules"] >= len(SERVERS) + 7 and kinds["postgres"] >= 3, kinds
    assert kinds["launcher"] == 1, kinds
    # var/ is the cell user's: private, passable by the lot user's group alone
    for path, mode, group in (
        (cfg.var, 0o710, lot_user.pw_gid),
        (cfg.run_dir, 0o710, lot_user.pw_gid),
        (cfg.var / "secrets", 0o710, lot_user.pw_gid),
        (cfg.var / "secrets" / "cell.key", 0o600, None),
        (cfg.var / "secrets" / "lot.key", 0o640, lot_user.pw_gid),
        (cfg.pg_dir, 0o700, None),
    ):
        st = path.stat()
        assert st.st_uid == gwc_user.pw_uid, f"{path} belongs to uid {st.st_uid}"
        assert st.st_mode & 0o7777 == mode, f"{path} is {st.st_mode & 0o7777:o}"
        assert group is None or st.st_gid == group, f"{path} has group {st.st_gid}"
    # what is left of root: nothing it runs, and `gwc status` as root works through the agent
    shown = gwc(root_cell.env, "status", "--json")
    assert shown.returncode == 0, shown.stderr
    assert all(r["state"] == "RUNNING" for r in json.loads(shown.stdout)), shown.stdout


def test_a_lot_script_runs_as_the_lot_user_with_the_lot_key_alone_and_makes_the_chess_order(
    root_cell: RootCell,
) -> None:
    cfg, env = root_cell.cfg, root_cell.env
    _, lot_user = _users()  # type: ignore[misc]
    script = root_cell.base / "probe.py"  # root's, 0644, in a folder of root's: trusted
    script.write_text(PROBE)

    def ok(*args: str) -> str:
        done = gwc(env, *args)
        assert done.returncode == 0, f"gwc {' '.join(args)}: {done.stderr}{done.stdout}"
        return done.stdout

    ok("script", "register", "probe", str(script), "--product", "probe_set")
    cmm = subprocess.Popen([sys.executable, "-m", "gwc", "machine", "start", "cmm_wc"], env=env)
    try:

        def homed() -> bool:
            for a in json.loads(gwc(env, "alarm", "list", "--json").stdout or "[]"):
                if a.get("alarm_id") == "HOME_CMM" and not a.get("cleared_at"):
                    gwc(env, "alarm", "clear", str(a["alarm_no"]))
            return cmm.poll() is not None

        wait_for(homed, 60, "the CMM to be homed and started", interval=0.2)
    finally:
        if cmm.poll() is None:
            cmm.kill()
        cmm.wait()
    made = json.loads(ok("order", "new", "--customer", "NJIT", "alum_chess_set=1", "probe_set=1", "--json"))
    entities = [e for lot in made["lots"] for e in lot["entities"]]
    assert len(entities) == 2
    # The lot user's launcher: exec'd by the agent as the lot user (its own command line: not a fork of
    # the agent, it holds nothing of the agent's), no capability, no group but its own.
    agent = int(json.loads((cfg.run_dir / "agent.pid").read_text())["pid"])
    launcher = wait_for(lambda: _launcher(cfg), 30, "the lot user's launcher")
    assert_lot_users(launcher, lot_user)
    assert _parent(launcher) == agent
    # Each script, waiting for its import: forked by the launcher, the agent's child (its subreaper)
    for e in entities:
        pid = wait_for(lambda e=e: _script_pid(cfg, e), 30, f"lot:{e} running")
        assert_lot_users(pid, lot_user)
        assert Path(f"/proc/{pid}/comm").read_text().strip() == f"lot:{e}", "forked by the launcher"
        assert "gwc.lot.launcher" in Path(f"/proc/{pid}/cmdline").read_text()
        assert _parent(pid) == agent

    def operator() -> bool:  # imports each waiting entity, exports each finished one
        states = dict(_query(cfg, "SELECT entity_id, state FROM lot_status WHERE entity_id = ANY(%s)", entities))
        assert "failed" not in states.values(), states
        for state, command in (("waiting_import", "import"), ("waiting_export", "export")):
            if state in states.values():
                ok(command, "--all")
        return all(s == "exported" for s in states.values()) and len(states) == len(entities)

    wait_for(operator, 90, "both lots exported", interval=0.2)
    probe = next(e for e in entities if "probe:" in _log(cfg, e))
    chess = next(e for e in entities if e != probe)
    line = next(x for x in _log(cfg, probe).splitlines() if "probe: {" in x)
    said = json.loads(line.split("probe: ", 1)[1])
    assert said["uid"] == lot_user.pw_uid
    tried = said["tried"]
    assert tried["read lot.key"] == "done" and tried["write its own log"] == "done", tried
    refused = {k: v for k, v in tried.items() if k not in ("read lot.key", "write its own log")}
    assert all(v == "Permission denied" for v in refused.values()), tried
    assert not (cfg.var / "planted").exists() and "forged" not in (cfg.log_dir / "ms.log").read_text()
    # its traveller, written by itself where the cell made room for it
    traveller = cfg.var / "lots" / f"entity-{probe}.json"
    assert traveller.stat().st_uid == lot_user.pw_uid and json.loads(traveller.read_text())["entity_id"] == probe
    # the chess set was measured on the CMM, by a script of the lot user's
    assert f"lot script of entity {chess} finished" in _log(cfg, chess), _log(cfg, chess)[-2000:]
    assert _query(cfg, "SELECT count(*) FROM machine_run_result WHERE machine_id = 'cmm_wc'")[0][0] >= 1
    checked = gwc(env, "check")
    assert checked.returncode == 0, checked.stdout + checked.stderr
    # The agent reaped each exec'd script as it does a fork: its exit status and whole CPU logged.
    text = next(cfg.log_dir.glob("agent-*.log")).read_text()
    for e in entities:
        cpu = re.search(rf"lot:{e}: RUNNING -> STOPPED .*exited 0, (\d+) ms of CPU: its work is done", text)
        assert cpu, f"lot:{e} not logged as ended"
        print(f"lot:{e} as {LOT_USER}, forked by its launcher: {cpu.group(1)} ms of CPU")
    # The launcher killed: a script is exec'd instead, a new launcher starts, and scripts fork from it.
    os.kill(launcher, signal.SIGKILL)
    made = json.loads(ok("order", "new", "--customer", "NJIT", "probe_set=1", "--json"))
    (execd,) = [e for lot in made["lots"] for e in lot["entities"]]
    pid = wait_for(lambda: _script_pid(cfg, execd), 30, f"lot:{execd} running")
    assert_lot_users(pid, lot_user)
    assert Path(f"/proc/{pid}/comm").read_text().strip() == "python", "exec'd while no launcher answers"
    again = wait_for(lambda: _launcher(cfg) not in (None, launcher) and _launcher(cfg), 30, "a new launcher")
    assert_lot_users(again, lot_user)
    wait_for(lambda: text_of(cfg).count("lot launcher ready") >= 2, 30, "the new launcher ready")
    # With its agent killed, `gwc stop` as root still stops a waiting script of the lot user's (CAP_KILL;
    # known as this cell's by its command line), and nothing of the cell is left.
    made = json.loads(ok("order", "new", "--customer", "NJIT", "probe_set=1", "--json"))
    (waiting,) = [e for lot in made["lots"] for e in lot["entities"]]
    pid = wait_for(lambda: _script_pid(cfg, waiting), 30, f"lot:{waiting} running")
    assert Path(f"/proc/{pid}/comm").read_text().strip() == f"lot:{waiting}", "forked by the new launcher"
    os.kill(agent, signal.SIGKILL)
    wait_for(lambda: not Path(f"/proc/{agent}").exists() or "Z" in Path(f"/proc/{agent}/stat").read_text(), 10)
    stopped = gwc(env, "stop", timeout=120)
    assert stopped.returncode == 0 and "refused" not in stopped.stdout, stopped.stdout + stopped.stderr
    for e in (execd, waiting):
        assert f"lot:{e}: stopped" in stopped.stdout or f"lot:{e}: killed" in stopped.stdout, stopped.stdout
    # (killed: gone, or a zombie until whoever adopted it, with its agent dead, reaps it)
    wait_for(lambda: _gone(pid), 5, "the lot script to be gone after `gwc stop`")
    assert not cell_processes(cfg), cell_processes(cfg)


@pytest.mark.timeout(400)
def test_bench_cell_runs_its_lot_scripts_as_the_lot_user_forked_by_its_launcher_or_execd() -> None:
    """`gwc bench cell --lot-user gwc-lot` as root: its cell's agent starts the scripts as that user, forked
    by the lot launcher, or each exec'd with `--no-launcher` ([lots] launcher = false); every lot done, and
    each script's whole CPU reported as the agent reaped it."""
    base = Path(tempfile.mkdtemp(prefix="gwc-bench-lots-", dir="/var/tmp"))
    base.chmod(0o755)  # the lot user walks to the bench's cell
    cell_user, _ = _users()  # type: ignore[misc]
    os.chown(base, cell_user.pw_uid, cell_user.pw_gid)  # the bench, as root, runs as the cell's user
    env = {k: v for k, v in os.environ.items() if k not in ("GWC_DATABASE_URL", "GWC_CONFIG")}
    env["GWC_VAR"] = str(base / "var")
    where = base / "bench"
    try:
        for flag, says in (("--launcher", "lot launcher ready"), ("--no-launcher", "no lot launcher")):
            args = ["--machines", "1", "--lots", "4", "--solo", "0", "--deaths", "0", "--idle", "0"]
            argv = [sys.executable, "-m", "gwc", "bench", "cell", *args, "--lot-user", LOT_USER, flag]
            done = subprocess.run(
                [*argv, "--dir", str(where), "--json"], env=env, capture_output=True, text=True, timeout=300
            )
            assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
            result = json.loads(done.stdout)
            assert result["lots"] == 4 and result["failed"] == 0 and result["check_held"], result
            assert result["script_cpu_ms"]["n"] == 4, result["script_cpu_ms"]
            agent = next((where / "log").glob("agent-*.log")).read_text()
            assert f"lot scripts run as user {LOT_USER}" in agent and says in agent, agent[-3000:]
            assert not list((where / "run").glob("*.pid"))  # the bench stopped its cell
    finally:
        shutil.rmtree(base, ignore_errors=True)


def assert_lot_users(pid: int, lot_user: pwd.struct_passwd) -> None:
    """The process is the lot user's alone: its uids and gids, no capability, no group but its own."""
    seen = ids(pid)
    assert seen["uids"] == {lot_user.pw_uid} and seen["gids"] == {lot_user.pw_gid}, seen
    assert seen["caps"] == 0 and seen["ambient"] == 0, seen
    groups = Path(f"/proc/{pid}/status").read_text().split("Groups:")[1].split("\n")[0].split()
    assert groups in ([], [str(lot_user.pw_gid)]), groups


def _parent(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])


def _launcher(cfg: Config) -> int | None:
    """The pid of this cell's lot launcher (its command line names it and the cell's var/), if one runs."""
    for d in Path("/proc").iterdir():
        with contextlib.suppress(OSError):
            argv = (d / "cmdline").read_bytes().split(b"\0")
            ours = d.name.isdigit() and b"gwc.lot.launcher" in argv and str(cfg.var.resolve()).encode() in argv
            if ours and (d / "comm").read_text().strip() == "lot-launcher":  # not a script it forked
                return int(d.name)
    return None


def text_of(cfg: Config) -> str:
    """The agent's log."""
    return next(cfg.log_dir.glob("agent-*.log")).read_text()


def _script_pid(cfg: Config, entity: int) -> int | None:
    try:
        pid = int(json.loads((cfg.run_dir / f"lot-{entity}.pid").read_text())["pid"])
    except (OSError, ValueError, KeyError):
        return None
    return pid if Path(f"/proc/{pid}").exists() else None


def _log(cfg: Config, entity: int) -> str:
    try:
        return (cfg.log_dir / f"lot-{entity}.log").read_text(errors="replace")
    except OSError:
        return ""


def _query(cfg: Config, sql: str, *params: Any) -> list[tuple[Any, ...]]:
    with psycopg.connect(db.database_url(cfg)) as conn:
        return conn.execute(sql, params).fetchall()


@pytest.mark.soak
@pytest.mark.timeout(1200)  # a new .venv (pip) and the demonstration
def test_the_quick_start_works_from_a_fresh_clone_as_root() -> None:
    """README's Quick start, `bin/demo`, as root in a fresh clone of this commit (a new .venv, the users
    already there or made): the demonstration succeeds, and it ran as `gwc` (var/demo is `gwc`'s). In
    a network namespace of its own: the demo's fixed bus port meets nobody else's."""
    base = Path(tempfile.mkdtemp(prefix="gwc-clone-", dir="/var/tmp"))
    base.chmod(0o755)
    clone = base / "gwc"
    try:
        head = subprocess.run(["git", "-C", str(PROJECT_ROOT), "rev-parse", "HEAD"], capture_output=True, text=True)
        subprocess.run(["git", "clone", "-q", str(PROJECT_ROOT), str(clone)], check=True, timeout=120)
        subprocess.run(["git", "-C", str(clone), "checkout", "-q", head.stdout.strip()], check=True)
        env = {k: v for k, v in os.environ.items() if not k.startswith(("GWC_", "VIRTUAL_ENV"))}
        # bin/demo sets up first: the new .venv's packages need the network, the demo must not have it
        setup = subprocess.run(["bin/setup"], cwd=clone, env=env, capture_output=True, text=True, timeout=900)
        assert setup.returncode == 0, (setup.stdout + setup.stderr)[-6000:]
        demo = subprocess.run(
            ["unshare", "--net", "sh", "-c", "ip link set lo up && exec bin/demo"],
            cwd=clone,
            env=env,
            capture_output=True,
            text=True,
            timeout=900,
        )
        out = demo.stdout + demo.stderr
        assert demo.returncode == 0, out[-6000:]
        assert "demonstration succeeded" in out
        gwc_user, _ = _users()  # type: ignore[misc]
        assert (clone / "var" / "demo").stat().st_uid == gwc_user.pw_uid
    finally:
        shutil.rmtree(base, ignore_errors=True)


def _gone(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except (OSError, IndexError):
        return True
