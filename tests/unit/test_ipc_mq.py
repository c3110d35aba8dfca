"""The WC<->ME channel: the fixed record, its two queues, and the errors it refuses to hide."""

from __future__ import annotations

import logging
import multiprocessing
import os
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import posix_ipc
import pytest

from gwc.errors import QueueError, QueueFull, QueueNotOurs, QueueTimeout
from gwc.ipc import mq
from gwc.ipc.codes import AckCode
from gwc.ipc.mq import (
    ALARM_TEXT_SIZE,
    FILE_NAME_SIZE,
    LAYOUT_SIZE,
    MAX_MESSAGES,
    RECIPE_ID_SIZE,
    Channel,
    MeMessage,
    MessageId,
    pack,
    queue_exists,
    queue_names,
    remove_queues,
    unpack,
)
from tests.harness import write_cell_config

LOG = logging.getLogger("test_mq")
MACHINE = "m1"


@pytest.fixture
def prefix() -> Iterator[str]:
    """A queue-name prefix of this test alone; every queue under it is gone after the test."""
    p = f"/gwct.{os.getpid()}.{uuid.uuid4().hex[:8]}"
    yield p
    remove_queues(p, [MACHINE, "m2"])
    assert not any(queue_exists(q) for q in queue_names(p, MACHINE)), "a test left its queues behind"


@pytest.fixture
def pair(prefix: str) -> Iterator[tuple[Channel, Channel]]:
    wc = Channel(prefix, MACHINE, "wc", LOG).open()
    me = Channel(prefix, MACHINE, "me", LOG).open()
    yield wc, me
    wc.close()
    me.close()


def full_message(mid: MessageId, seq: int = 7) -> MeMessage:
    """Every field used, up to the last byte of its slot, with multi-byte characters."""
    return MeMessage(
        mid,
        file_name="/var/" + "f" * (FILE_NAME_SIZE - 7) + "é",
        recipe_id="r" * (RECIPE_ID_SIZE - 2) + "é",
        ack_code=AckCode.BAD_MESSAGE,
        alarm_text="ä" * (ALARM_TEXT_SIZE // 2),
        seq=seq,
    )


def _echo_me(prefix: str, machine: str) -> None:
    """The other process: answer each record with itself plus Ack_OK, until ME_SHUT."""
    with Channel(prefix, machine, "me", LOG) as ch:
        while True:
            msg = ch.receive(timeout=10)
            if msg.message_id == MessageId.ME_SHUT:
                ch.send(msg.reply(AckCode.ACK_OK, message_id=MessageId.ME_SHUT_C))
                return
            ch.send(msg.reply(AckCode.ACK_OK))


# ----------------------------------------------------------------------------- the record


def test_layout_is_the_documented_396_bytes() -> None:
    assert LAYOUT_SIZE == 396
    data = pack(
        MeMessage(
            MessageId.SETUP_RUN,
            file_name="/a",
            recipe_id="r1",
            ack_code=AckCode.ACK_OK,
            alarm_text="HOME",
            seq=0x01020304,
        )
    )
    assert data[0:4] == b"GWME"
    assert data[4:6] == b"\x00\x01"  # layout version
    assert data[6:8] == b"\x00\x04"  # SETUP_RUN
    assert data[8:12] == b"\x01\x02\x03\x04"  # seq, big-endian
    assert data[12:24] == b"ACK_OK" + b"\0" * 6
    assert data[24:56].rstrip(b"\0") == b"r1"
    assert data[56:312].rstrip(b"\0") == b"/a"
    assert data[312:392].rstrip(b"\0") == b"HOME"


def test_every_field_round_trips_at_full_length() -> None:
    for mid in MessageId:
        msg = full_message(mid)
        assert unpack(pack(msg)) == msg


@pytest.mark.parametrize(
    "field,size", [("file_name", FILE_NAME_SIZE), ("recipe_id", RECIPE_ID_SIZE), ("alarm_text", ALARM_TEXT_SIZE)]
)
def test_oversize_field_is_refused_not_truncated(field: str, size: int) -> None:
    assert getattr(unpack(pack(MeMessage(MessageId.NO_MESSAGE, **{field: "x" * size}))), field) == "x" * size
    with pytest.raises(QueueError, match=f"{field} is {size + 1} bytes"):
        pack(MeMessage(MessageId.NO_MESSAGE, **{field: "x" * (size + 1)}))
    with pytest.raises(QueueError, match=f"{field} is {size + 1} bytes"):  # bytes count, not characters
        pack(MeMessage(MessageId.NO_MESSAGE, **{field: "x" * (size - 1) + "é"}))


def test_nul_unknown_ack_code_and_bad_seq_are_refused() -> None:
    with pytest.raises(QueueError, match="NUL"):
        pack(MeMessage(MessageId.NO_MESSAGE, recipe_id="a\0b"))
    with pytest.raises(QueueError, match="unknown ack code"):
        pack(MeMessage(MessageId.NO_MESSAGE, ack_code="MAYBE"))  # type: ignore[arg-type]
    with pytest.raises(QueueError, match="32 bits"):
        pack(MeMessage(MessageId.NO_MESSAGE, seq=2**32))


@pytest.mark.parametrize(
    "damage,why",
    [
        (lambda d: d[:-1], "395 bytes"),
        (lambda d: b"XXXX" + d[4:], "magic"),
        (lambda d: d[:4] + b"\x00\x09" + d[6:], "version 9"),
        (lambda d: d[:30] + bytes([d[30] ^ 0x40]) + d[31:], "CRC"),
    ],
)
def test_garbled_record_is_a_clear_error(damage, why: str) -> None:
    data = pack(MeMessage(MessageId.START_RUN, recipe_id="abc", file_name="/x"))
    with pytest.raises(QueueError, match=why):
        unpack(damage(data))


def test_unknown_message_id_with_good_crc_is_refused() -> None:
    import struct
    import zlib

    body = bytearray(pack(MeMessage(MessageId.NO_MESSAGE))[:-4])
    body[6:8] = (99).to_bytes(2, "big")
    with pytest.raises(QueueError, match="unknown message id 99"):
        unpack(bytes(body) + struct.pack("!I", zlib.crc32(bytes(body))))


# ----------------------------------------------------------------------------- the queues


def test_every_message_id_round_trips_across_two_processes(prefix: str) -> None:
    ctx = multiprocessing.get_context("spawn")
    child = ctx.Process(target=_echo_me, args=(prefix, MACHINE))
    with Channel(prefix, MACHINE, "wc", LOG) as wc:
        child.start()
        try:
            for seq, mid in enumerate(MessageId, 1):
                if mid == MessageId.ME_SHUT:
                    continue
                sent = full_message(mid, seq)
                wc.send(sent)
                back = wc.receive(timeout=10)
                assert back == sent.reply(AckCode.ACK_OK), mid
            wc.send(MeMessage(MessageId.ME_SHUT, seq=99))
            last = wc.receive(timeout=10)
            assert (last.message_id, last.seq, last.ack_code) == (MessageId.ME_SHUT_C, 99, AckCode.ACK_OK)
        finally:
            child.join(10)
            if child.is_alive():
                child.kill()
    assert child.exitcode == 0


def test_receive_times_out_and_poll_does_not_wait(pair: tuple[Channel, Channel]) -> None:
    wc, me = pair
    t0 = time.monotonic()
    with pytest.raises(QueueTimeout):
        me.receive(timeout=0.2)
    assert 0.15 <= time.monotonic() - t0 < 2.0
    t0 = time.monotonic()
    assert me.poll() is None
    assert time.monotonic() - t0 < 0.1
    wc.send(MeMessage(MessageId.ME_START, seq=3))
    assert me.poll() == MeMessage(MessageId.ME_START, seq=3)


def test_full_queue_is_an_error_and_loses_nothing(pair: tuple[Channel, Channel]) -> None:
    wc, me = pair
    for i in range(MAX_MESSAGES):
        wc.send(MeMessage(MessageId.NO_MESSAGE, seq=i))
    with pytest.raises(QueueFull, match="full"):
        wc.send(MeMessage(MessageId.NO_MESSAGE, seq=99))
    t0 = time.monotonic()
    with pytest.raises(QueueFull):
        wc.send(MeMessage(MessageId.NO_MESSAGE, seq=99), timeout=0.2)  # waits its deadline, then refuses
    assert time.monotonic() - t0 >= 0.15
    assert [me.receive(0).seq for _ in range(MAX_MESSAGES)] == list(range(MAX_MESSAGES))
    assert me.poll() is None


def test_garbled_record_on_the_queue_is_refused_and_the_next_one_read(pair: tuple[Channel, Channel]) -> None:
    wc, me = pair
    raw = posix_ipc.MessageQueue(wc.out_name)
    try:
        raw.send(b"\x00" * LAYOUT_SIZE)
    finally:
        raw.close()
    wc.send(MeMessage(MessageId.SETUP_RUN, seq=5))
    with pytest.raises(QueueError, match="garbled"):
        me.receive(timeout=1)
    assert me.receive(timeout=1).seq == 5


def test_oversize_field_is_refused_before_anything_is_queued(pair: tuple[Channel, Channel]) -> None:
    wc, me = pair
    with pytest.raises(QueueError, match="file_name"):
        wc.send(MeMessage(MessageId.SETUP_RUN, file_name="/" + "x" * FILE_NAME_SIZE))
    assert wc.pending() == (0, 0)


def test_either_half_creates_the_queues_and_they_survive_a_restart(prefix: str) -> None:
    me = Channel(prefix, MACHINE, "me", LOG).open()  # the ME first this time
    me.send(MeMessage(MessageId.RUN_COMPL, file_name="/r", seq=1))
    me.close()  # the ME "dies": its record waits in the queue
    with Channel(prefix, MACHINE, "wc", LOG) as wc:
        assert wc.receive(timeout=1).file_name == "/r"
        wc.send(MeMessage(MessageId.NO_MESSAGE, seq=2))
        with Channel(prefix, MACHINE, "me", LOG) as me2:  # a restarted ME finds the WC's request
            assert me2.receive(timeout=1).seq == 2
    assert all(queue_exists(q) for q in queue_names(prefix, MACHINE))


def test_queue_of_another_layout_is_refused(prefix: str) -> None:
    to_me, _ = queue_names(prefix, MACHINE)
    posix_ipc.MessageQueue(to_me, posix_ipc.O_CREX, max_messages=2, max_message_size=128).close()
    with pytest.raises(QueueError, match="128 bytes"):
        Channel(prefix, MACHINE, "wc", LOG).open()


def test_bad_names_and_sides_are_refused(prefix: str) -> None:
    with pytest.raises(QueueError):
        queue_names(prefix, "a/b")
    with pytest.raises(QueueError):
        Channel(prefix, MACHINE, "both", LOG)  # type: ignore[arg-type]
    with pytest.raises(QueueError, match="not open"):
        Channel(prefix, MACHINE, "wc", LOG).send(MeMessage(MessageId.NO_MESSAGE))


def test_drain_throws_away_stale_records(pair: tuple[Channel, Channel]) -> None:
    wc, me = pair
    for i in range(3):
        wc.send(MeMessage(MessageId.NO_MESSAGE, seq=i))
    assert me.drain() == 3
    assert me.poll() is None


def test_queues_are_gone_after_gwc_stop(tmp_path: Path) -> None:
    cfg = write_cell_config(
        tmp_path / "var",
        "postgresql://gwc@/none?host=/nonexistent",
        machines=[{"id": "wc1", "kind": "dummy"}, {"id": "wc2", "kind": "dummy"}],
    )
    for mid in ("wc1", "wc2"):
        Channel(cfg.ipc_prefix, mid, "wc", LOG).open().close()
        assert all(queue_exists(q) for q in queue_names(cfg.ipc_prefix, mid))
    env = dict(os.environ, GWC_CONFIG=str(cfg.path), GWC_VAR=str(cfg.var))
    env.pop("GWC_DATABASE_URL", None)
    try:
        done = subprocess.run(
            [sys.executable, "-m", "gwc", "stop"], env=env, capture_output=True, text=True, timeout=60
        )
        assert done.returncode == 0, done.stderr
        for mid in ("wc1", "wc2"):
            assert not any(queue_exists(q) for q in queue_names(cfg.ipc_prefix, mid))
    finally:
        mq.remove_queues(cfg.ipc_prefix, ["wc1", "wc2"])


def _squat(name: str, uid: int, mode: int) -> None:
    """Another user (uid) making a queue of the cell's name before the cell does."""
    if uid:
        os.setuid(uid)
    os.umask(0)
    posix_ipc.MessageQueue(name, posix_ipc.O_CREX, mode=mode, max_messages=2, max_message_size=mq.LAYOUT_SIZE).close()


@pytest.mark.skipif(os.geteuid() != 0, reason="makes a queue as another user")
@pytest.mark.parametrize("uid, mode", [(65534, 0o600), (65534, 0o666), (0, 0o666), (0, 0o622)])
def test_a_queue_the_cell_did_not_make_is_refused_never_used(prefix: str, uid: int, mode: int) -> None:
    to_me, from_me = queue_names(prefix, MACHINE)
    squatter = multiprocessing.get_context("fork").Process(target=_squat, args=(to_me, uid, mode))
    squatter.start()
    squatter.join()
    assert squatter.exitcode == 0
    with pytest.raises(QueueNotOurs, match=f"{to_me} exists but is not the cell's"):
        Channel(prefix, MACHINE, "wc", LOG).open()
    with pytest.raises(QueueError, match="not the cell's"):
        Channel(prefix, MACHINE, "me", LOG).open()
    assert posix_ipc.MessageQueue(to_me).current_messages == 0  # nothing was written to it


def test_the_cells_own_queues_are_made_exclusively_0600_and_reopened(prefix: str) -> None:
    with Channel(prefix, MACHINE, "wc", LOG) as wc, Channel(prefix, MACHINE, "me", LOG) as me:
        for q in (wc._out, wc._in):
            assert q is not None and os.fstat(q.mqd).st_mode & 0o777 == 0o600
        wc.send(MeMessage(MessageId.NO_MESSAGE, seq=1))
        assert me.receive(1).seq == 1
