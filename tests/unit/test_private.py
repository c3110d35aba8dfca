"""What the cell keeps to itself on its host (gwc/private.py): var/ and var/run its own, pid files and
locks never through a link nor someone else's, and `gwc stop` signalling only the cell's processes."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from gwc import cell, private
from gwc.config import Config
from gwc.private import NotPrivate
from gwc.soak.private_config import write_config
from tests.harness import wait_for

NOBODY = 65534
as_root = pytest.mark.skipif(os.geteuid() != 0, reason="makes files as another user")


@pytest.fixture
def cfg(tmp_path: Path) -> Config:
    return write_config(tmp_path / "etc" / "cell.toml", {"cell": {"name": "t", "var": str(tmp_path / "var")}})


@pytest.fixture
def stranger() -> Iterator[subprocess.Popen[bytes]]:
    """A process of the host that is not the cell's (no GWC_VAR of it), in a session of its own."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("GWC_")}
    p = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"], env=env, start_new_session=True)
    yield p
    p.kill()
    p.wait()


def plant_pid_file(cfg: Config, name: str, pid: int) -> None:
    ticks = int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19])
    cell.pid_file(cfg, name).write_text(json.dumps({"pid": pid, "ticks": ticks, "since": "x", "argv": []}))


def _state(pid: int) -> str:
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]


def test_var_and_var_run_are_made_the_cells_alone_and_an_old_1777_is_closed(cfg: Config) -> None:
    cfg.run_dir.mkdir(parents=True, exist_ok=True)
    cfg.run_dir.chmod(0o1777)  # what older versions left
    private.secure_var(cfg)
    for d in (cfg.var, cfg.run_dir):
        assert stat.S_IMODE(d.stat().st_mode) in (0o700, 0o710)  # 0710: root and the embedded cluster


@as_root
def test_a_folder_of_another_user_or_a_link_is_refused_never_used(cfg: Config, tmp_path: Path) -> None:
    cfg.run_dir.mkdir(parents=True)
    os.chown(cfg.run_dir, NOBODY, NOBODY)
    with pytest.raises(NotPrivate, match=f"belongs to uid {NOBODY}"):
        private.secure_var(cfg)
    cfg.run_dir.rmdir()
    cfg.run_dir.symlink_to(tmp_path)
    with pytest.raises(NotPrivate, match="not a folder"):
        private.secure_var(cfg)


def test_a_pid_file_is_never_written_through_a_planted_link(cfg: Config, tmp_path: Path) -> None:
    private.secure_var(cfg)
    victim = tmp_path / "victim"
    victim.write_text("root's own\n")
    cell.pid_file(cfg, "msched").symlink_to(victim)
    cell.write_pid_file(cfg, "msched", os.getpid(), ["x"])
    assert victim.read_text() == "root's own\n"
    assert not cell.pid_file(cfg, "msched").is_symlink() and cell.read_pid(cfg, "msched").pid == os.getpid()
    assert stat.S_IMODE(cell.pid_file(cfg, "msched").stat().st_mode) == private.PID_MODE


@as_root
def test_a_pid_file_or_lock_of_another_user_is_refused(cfg: Config) -> None:
    private.secure_var(cfg)
    planted = cell.pid_file(cfg, "ms")
    planted.write_text(json.dumps({"pid": 1, "ticks": 1}))
    os.chown(planted, NOBODY, NOBODY)
    assert cell.read_pid(cfg, "ms").refused and cell.read_pid(cfg, "ms").pid is None
    assert cell.stop_proc(cfg, "ms").startswith(cell.REFUSED) and not planted.exists()
    lock = cfg.run_dir / "agent.lock"
    lock.touch()
    os.chown(lock, NOBODY, NOBODY)
    with pytest.raises(NotPrivate):
        private.open_lock(lock)
    lock.unlink()
    os.close(private.open_lock(lock))
    assert stat.S_IMODE(lock.stat().st_mode) == 0o600


def test_gwc_stop_never_signals_what_is_not_the_cells(cfg: Config, stranger: subprocess.Popen[bytes]) -> None:
    private.secure_var(cfg)
    for name, pid in (("ms", stranger.pid), ("cas", 1)):
        plant_pid_file(cfg, name, pid)
        assert cell.read_pid(cfg, name).alive  # a well-made pid file: its start time matches
        what = cell.stop_proc(cfg, name, grace=0.2)
        assert what.startswith(cell.REFUSED) and ("not started for this cell" in what or "never" in what), what
        assert not cell.pid_file(cfg, name).exists()
    assert stranger.poll() is None  # alive: never signalled
    assert private.not_the_cells(cfg, os.getpid()) is not None  # pytest has no GWC_VAR of this cell


def test_gwc_stop_signals_the_cells_own_process(cfg: Config) -> None:
    proc = cell.Proc("probe", command=(sys.executable, "-c", "import time; time.sleep(60)"))
    child = cell.spawn_process(cfg, proc)
    try:
        assert private.not_the_cells(cfg, child.pid) is None
        assert cell.stop_proc(cfg, "probe", grace=5) == "stopped"
    finally:
        child.kill()
        child.wait()


def test_a_process_that_exits_as_gwc_stop_looks_at_it_is_stopped_not_refused(
    cfg: Config, monkeypatch: pytest.MonkeyPatch
) -> None:
    """stop_cell signals every lot script before stop_proc looks at each: one may turn zombie between
    stop_proc's liveness check and not_the_cells, whose empty command line would read as not the cell's."""
    proc = cell.Proc("probe", command=(sys.executable, "-c", "import time; time.sleep(60)"))
    child = cell.spawn_process(cfg, proc)
    looked = private.not_the_cells

    def exits_meanwhile(c: Config, pid: int) -> str | None:
        child.send_signal(9)
        wait_for(lambda: _state(pid) == "Z", 5, "the probe to be a zombie")  # its parent, this test, reaps it later
        return looked(c, pid)

    monkeypatch.setattr(cell, "not_the_cells", exits_meanwhile)
    try:
        assert looked(cfg, child.pid) is None
        assert cell.stop_proc(cfg, "probe", grace=5) == "stopped"
        assert not cell.pid_file(cfg, "probe").exists()
    finally:
        child.kill()
        child.wait()


@as_root
def test_a_lot_script_another_user_could_have_written_is_refused(tmp_path: Path) -> None:
    from gwc.lot.errors import LotError
    from gwc.lot.run import load_script

    tmp_path.chmod(0o755)
    script = tmp_path / "pawn.py"
    script.write_text("def main(entity):\n    pass\n")
    assert callable(load_script(script).main)  # root's, 0644, in root's folders
    for change, says in (
        (lambda: script.chmod(0o666), "-rw-rw-rw-"),
        (lambda: os.chown(script, NOBODY, -1), f"owner uid {NOBODY}"),
        (lambda: tmp_path.chmod(0o777), "drwxrwxrwx"),  # anyone could put another file in its place
    ):
        change()
        with pytest.raises(LotError, match=f"{says}.*refused"):
            load_script(script)
        script.chmod(0o644)
        os.chown(script, 0, -1)
        tmp_path.chmod(0o755)
    sticky = tmp_path / "sticky"
    sticky.mkdir(mode=0o1777)
    sticky.chmod(0o1777)  # like /tmp: its users cannot replace each other's files
    (sticky / "pawn.py").write_text("def main(entity):\n    pass\n")
    assert callable(load_script(sticky / "pawn.py").main)
