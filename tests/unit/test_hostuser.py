"""gwc.hostuser: who the cell and its lot scripts run as, and the few capabilities the agent keeps."""

from __future__ import annotations

import json
import os
import pwd
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from gwc import hostuser, private
from gwc.config import Config
from gwc.soak.private_config import write_config

as_root = pytest.mark.skipif(os.geteuid() != 0, reason="becomes another user")


def _exists(name: str) -> bool:
    try:
        pwd.getpwnam(name)
    except KeyError:
        return False
    return True


needs_users = pytest.mark.skipif(
    not (_exists(hostuser.CELL_USER) and _exists(hostuser.LOT_USER)), reason="bin/setup as root makes the users"
)


def config(tmp_path: Path, **sections: Any) -> Config:
    tmp_path.chmod(0o755)
    doc = {"cell": {"name": "t", "var": str(tmp_path / "var")}, **sections}
    return write_config(tmp_path / "etc" / "cell.toml", doc)


@pytest.fixture
def reachable() -> Iterator[Path]:
    """A folder the cell's user may walk to (pytest's own, under /tmp/pytest-of-root, is root's alone)."""
    where = Path(tempfile.mkdtemp(prefix="gwc-hostuser-", dir="/var/tmp"))
    try:
        yield where
    finally:
        shutil.rmtree(where, ignore_errors=True)


def in_child(fn: Callable[[], Any]) -> Any:
    """fn() in a forked child (it may drop privileges for good); its JSON result."""
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        code = 1
        try:
            os.close(r)
            os.write(w, json.dumps(fn()).encode())
            code = 0
        finally:
            os._exit(code)
    os.close(w)
    with os.fdopen(r) as f:
        out = f.read()
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0, "the child failed"
    return json.loads(out)


def test_the_users_default_to_gwc_and_gwc_lot_and_a_private_cell_runs_as_its_starter(tmp_path: Path) -> None:
    private = config(tmp_path)  # write_config: a private cell ([cell] user = "")
    assert (hostuser.cell_user_name(private), hostuser.lot_user_name(private)) == ("", "")
    shipped = config(tmp_path, cell={"name": "t", "var": str(tmp_path / "var"), "user": "gwc"})
    assert (hostuser.cell_user_name(shipped), hostuser.lot_user_name(shipped)) == ("gwc", "gwc-lot")
    own = config(tmp_path, cell={"name": "t", "user": "gwc"}, lots={"user": "someone"})
    assert hostuser.lot_user_name(own) == "someone"
    with pytest.raises(hostuser.HostUserError, match="not a user name"):
        hostuser.cell_user_name(config(tmp_path, cell={"name": "t", "user": 7}))


@as_root
def test_a_private_cell_started_as_root_stays_root(tmp_path: Path) -> None:
    cfg = config(tmp_path)
    assert in_child(lambda: (hostuser.become_cell_user(cfg), os.geteuid())[1]) == 0


@as_root
@needs_users
def test_root_becomes_the_cell_user_keeping_only_the_capabilities_asked_and_passing_none_on(reachable: Path) -> None:
    tmp_path = reachable
    cfg = config(tmp_path, cell={"name": "t", "var": str(tmp_path / "var"), "user": "gwc"})
    (tmp_path / "var" / "pg").mkdir(parents=True)  # an older var/: root's, its cluster another's
    (tmp_path / "var" / "log.txt").write_text("x")
    gwc = pwd.getpwnam("gwc")
    status = [sys.executable, "-c", "print(open('/proc/self/status').read())"]

    def capeff(text: str) -> int:
        return int(next(x for x in text.splitlines() if x.startswith("CapEff:")).split()[1], 16)

    def drop() -> dict[str, Any]:
        hostuser.become_cell_user(cfg, hostuser.AGENT_CAPS)
        plain = subprocess.run(status, capture_output=True, text=True, check=True).stdout
        with hostuser.ambient(hostuser.AGENT_CAPS):
            handed = subprocess.run(status, capture_output=True, text=True, check=True).stdout
        after = subprocess.run(status, capture_output=True, text=True, check=True).stdout
        return {
            "ids": [os.getresuid(), os.getresgid()],
            "caps": hostuser.effective_caps(),
            "child": capeff(plain),
            "handed": capeff(handed),
            "after": capeff(after),
            "lot": hostuser.lot_user(cfg) is not None,
        }

    got = in_child(drop)
    assert got["ids"] == [[gwc.pw_uid] * 3, [gwc.pw_gid] * 3]
    want = sum(1 << c for c in hostuser.AGENT_CAPS)
    assert got["caps"] == want, f"{got['caps']:x}"
    assert got["child"] == 0 and got["after"] == 0, "an exec'd child inherits nothing"
    assert got["handed"] == want, "but what it execs with ambient() gets them (the agent, from gwc start)"
    assert got["lot"], "with CAP_SETUID and CAP_SETGID it may start lot scripts as gwc-lot"
    for p in (tmp_path / "var", tmp_path / "var" / "pg", tmp_path / "var" / "log.txt"):
        assert p.lstat().st_uid == gwc.pw_uid, p


@as_root
@needs_users
def test_a_cell_user_that_cannot_reach_var_leaves_the_cell_as_root_with_a_warning_naming_the_folder(
    tmp_path: Path,
) -> None:
    # A checkout the cell's user cannot enter (under root's 0700 home, say) still runs, as the Quick
    # start must: as the one who started it, said on standard error.
    cfg = config(tmp_path, cell={"name": "t", "var": str(tmp_path / "closed" / "var"), "user": "gwc"})
    (tmp_path / "closed").mkdir(exist_ok=True)
    (tmp_path / "closed").chmod(0o700)

    def drop() -> str:
        import contextlib
        import io

        err = io.StringIO()
        with contextlib.redirect_stderr(err):
            hostuser.become_cell_user(cfg)
        return f"{os.geteuid()} {err.getvalue()}"

    said = in_child(drop)
    assert said.startswith("0 "), said
    assert "cannot enter" in said and str(tmp_path / "closed") in said and "runs as root, not gwc" in said, said


@as_root
def test_a_missing_cell_user_is_refused_with_what_to_do(tmp_path: Path) -> None:
    cfg = config(tmp_path, cell={"name": "t", "user": "gwc-nobody-here"})
    with pytest.raises(hostuser.HostUserError, match="bin/setup"):
        hostuser.become_cell_user(cfg)


@as_root
@needs_users
def test_gwc_stop_knows_a_lot_script_of_the_lot_user_by_its_command_line(reachable: Path) -> None:
    cfg = config(reachable, cell={"name": "t", "var": str(reachable / "var"), "user": "gwc"})
    (reachable / "other").mkdir()
    other = config(reachable / "other", cell={"name": "t", "var": str(reachable / "other" / "var"), "user": "gwc"})
    lot = pwd.getpwnam(hostuser.LOT_USER)
    nap = [sys.executable, "-c", "import time; time.sleep(60)", "gwc.lot.run", "--entity", "1", "--var"]
    ours = subprocess.Popen([*nap, str(cfg.var)], user=lot.pw_uid, group=lot.pw_gid, extra_groups=[])
    theirs = subprocess.Popen([*nap, str(other.var)], user=lot.pw_uid, group=lot.pw_gid, extra_groups=[])
    try:

        def judged() -> list[str | None]:
            hostuser.become_cell_user(cfg, hostuser.STOP_CAPS)
            return [private.not_the_cells(cfg, ours.pid), private.not_the_cells(cfg, theirs.pid)]

        mine, not_mine = in_child(judged)
        assert mine is None
        assert not_mine is not None and "not a lot script of this cell" in not_mine, not_mine
    finally:
        for p in (ours, theirs):
            p.kill()
            p.wait()


def test_a_traveller_is_never_read_through_a_link(tmp_path: Path) -> None:
    """var/lots is the lot user's to write: a link it plants must not have the cell read (and show) a
    file of the cell's own."""
    from gwc.lot.model import read_traveller, traveller_path

    cfg = config(tmp_path)
    secret = tmp_path / "secret.json"
    secret.write_text('{"entity_id": 7, "key": "the cell key"}')
    traveller_path(cfg, 7).parent.mkdir(parents=True)
    traveller_path(cfg, 7).symlink_to(secret)
    assert read_traveller(cfg, 7) is None
    traveller_path(cfg, 8).write_text('{"entity_id": 8}')
    assert read_traveller(cfg, 8) == {"entity_id": 8}
