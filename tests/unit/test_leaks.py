"""The leak check every test runs under (tests/leaks.py): what it finds, and that a clean test passes."""

from __future__ import annotations

import logging
import socket
import subprocess
from pathlib import Path

import pytest

from gwc.ipc.mq import Channel, queue_exists, queue_names, remove_queues
from tests.conftest import make_config
from tests.harness import wait_for
from tests.leaks import Leaked, leak_check

LOG = logging.getLogger("test_leaks")


def test_a_clean_test_passes(tmp_path: Path) -> None:
    with leak_check(tmp_path):
        subprocess.run(["true"], check=True)
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM).close()


def test_a_detached_process_left_running_fails_the_test_and_is_killed(tmp_path: Path) -> None:
    with pytest.raises(Leaked, match=r"process \d+: sleep 60"), leak_check(tmp_path):
        child = subprocess.Popen(["sleep", "60"], start_new_session=True)
        # Until its exec is done the child's /proc entry may not be readable: a leak is an older process.
        wait_for(lambda: Path(f"/proc/{child.pid}/cmdline").read_bytes().startswith(b"sleep"), 5, "sleep to run")
    assert child.wait(timeout=10) < 0  # killed by the check


def test_a_socket_left_open_fails_the_test(tmp_path: Path) -> None:
    kept: list[socket.socket] = []
    try:
        with pytest.raises(Leaked, match="open socket:"), leak_check(tmp_path):
            kept.append(socket.socket(socket.AF_INET, socket.SOCK_DGRAM))
    finally:
        for s in kept:
            s.close()


def test_a_queue_left_by_a_cell_fails_the_test(tmp_path: Path) -> None:
    cfg = make_config(tmp_path / "cell", None, machine=[{"id": "m1", "kind": "dummy"}])
    try:
        with pytest.raises(Leaked, match="queue /gwc"), leak_check(tmp_path):
            Channel(cfg.ipc_prefix, "m1", "wc", LOG).open().close()
    finally:
        remove_queues(cfg.ipc_prefix, ["m1"])
    assert not any(queue_exists(q) for q in queue_names(cfg.ipc_prefix, "m1"))
