"""The lot user's launcher (gwc/lot/launcher.py): what it answers to a request it cannot read, how its
double fork hands a script to the agent (a subreaper) to wait for, and the sweep that reaps only the
orphans no one waits for. The subreaper runs in a child Python of its own, so pytest never becomes one;
the launcher as the lot user, in a whole cell, is tests/e2e/test_cell_user.py's."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from gwc.errors import ConfigError
from gwc.lot.launcher import launcher_wanted, serve
from gwc.soak.private_config import write_config

ROOT = Path(__file__).resolve().parents[2]


def run_python(code: str) -> dict[str, object]:
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    return dict(json.loads(done.stdout.strip().splitlines()[-1]))


def test_a_request_the_launcher_cannot_read_is_answered_why_and_its_socket_end_ends_it() -> None:
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    ended: list[int] = []
    serving = threading.Thread(target=lambda: ended.append(serve(None, theirs)))  # type: ignore[arg-type]
    serving.start()
    try:
        ours.settimeout(10)
        assert ours.recv(64) == b"R\n"
        for request, fds in ((b"E 12\n", []), (b"E twelve\n", [0]), (b"fork everything", [0]), (b"E 1 2\n", [0])):
            socket.send_fds(ours, [request], [os.dup(fd) for fd in fds])
            said = ours.recv(256)
            assert said.startswith(b"X not a request: "), said
    finally:
        ours.close()
        serving.join(10)
        theirs.close()
    assert ended == [0] and not serving.is_alive()


def test_the_double_fork_hands_the_script_to_the_subreaper_which_reaps_it_with_its_status() -> None:
    said = run_python(
        """
import ctypes, json, os, time
from gwc.lot import launcher

assert ctypes.CDLL(None).prctl(launcher.PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) == 0
def child(cfg, entity_id, out, inherited):  # the script: waits for its go, then exits as its own
    os.read(out, 1)
    os._exit(entity_id)
launcher.fork_child = child
r, w = os.pipe()
pid = launcher.fork_script(None, 7, r)  # returned: the middle process is gone, the script is ours
parent = int(open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[1])
os.write(w, b"g")
_, status, usage = os.wait4(pid, 0)
print(json.dumps({"me": os.getpid(), "parent": parent, "code": os.waitstatus_to_exitcode(status)}))
"""
    )
    assert said["parent"] == said["me"] and said["code"] == 7, said


def test_the_sweep_reaps_an_orphan_no_one_waits_for_and_leaves_the_agents_own() -> None:
    said = run_python(
        """
import ctypes, json, logging, os, time
from gwc.lot import launcher

assert ctypes.CDLL(None).prctl(launcher.PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) == 0
def orphan():  # a process whose parent exits at once: the subreaper's, as a script's own child would be
    r, w = os.pipe()
    middle = os.fork()
    if middle == 0:
        pid = os.fork()
        if pid == 0:
            os._exit(0)
        os.write(w, str(pid).encode())
        os._exit(0)
    pid = int(os.read(r, 32))
    os.waitpid(middle, 0)
    while open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[0] != "Z":
        time.sleep(0.01)
    return pid
waited = orphan()
sweeper = launcher.LotLauncher(None, None, logging.getLogger("t"), lambda: {waited})
kept = sweeper.sweep()  # the agent's own zombie first: the sweep stops at it
stray = orphan()
os.waitpid(waited, 0)  # the agent reaps its own
swept = sweeper.sweep()
print(json.dumps({"kept": kept, "swept": swept, "stray": stray, "gone": not os.path.exists(f"/proc/{stray}")}))
"""
    )
    assert said["kept"] == [] and said["swept"] == [said["stray"]] and said["gone"], said


def test_lots_launcher_is_on_unless_set_false_and_anything_else_is_refused(tmp_path: Path) -> None:
    def cfg(lots: dict[str, object]) -> object:
        return write_config(tmp_path / "etc" / "cell.toml", {"cell": {"var": str(tmp_path / "var")}, "lots": lots})

    assert launcher_wanted(cfg({})) is True  # type: ignore[arg-type]
    assert launcher_wanted(cfg({"launcher": False})) is False  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match=r"\[lots\] launcher = 'no' is not true or false"):
        launcher_wanted(cfg({"launcher": "no"}))  # type: ignore[arg-type]
