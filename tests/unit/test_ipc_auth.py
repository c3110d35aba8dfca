"""The seal on every datagram (gwc/ipc/auth.py) and the cell's keys (gwc/ipc/keys.py), in one process."""

from __future__ import annotations

import collections
import json
import logging
import os
import stat
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from gwc.cli import cli
from gwc.config import BusConfig
from gwc.errors import BusError, MessageError
from gwc.ipc import auth, catalogue, keys, wire
from gwc.ipc.auth import Guard
from gwc.ipc.codes import AckCode
from tests.conftest import make_config

LOG = logging.getLogger("gwc.test.auth")


def cfg_in(where: Path, **kw: float) -> BusConfig:
    cfg = BusConfig(key_file=str(where / "cell.key"), lot_key_file=str(where / "lot.key"), **kw)  # type: ignore[arg-type]
    keys.ensure(cfg)
    return cfg


def guard(cfg: BusConfig, name: str) -> Guard:
    return Guard(cfg, name, LOG, collections.Counter())


def body(src: str = "ms", inc: int = 5, **kw: object) -> bytes:
    fields = {"kind": "msg", "seq": 1, "conv": f"{src}.5.1", "cls": "UPD_ME_ST", "msg": "Update_ME_Status"} | kw
    return wire.encode(wire.Envelope(src=src, inc=inc, **fields))  # type: ignore[arg-type]


def test_key_files_are_private_and_hold_what_each_role_may_have(tmp_path: Path) -> None:
    cfg = cfg_in(tmp_path)
    for f in ("cell.key", "lot.key"):
        assert stat.S_IMODE(os.stat(tmp_path / f).st_mode) == 0o600
    _, lot = keys.load(cfg, "lot")
    _, cell = keys.load(cfg, "module")
    assert {k.role for k in lot.keys} == {"lot"} and {k.role for k in cell.keys} == {"lot", "module"}
    assert lot.cell_id == cell.cell_id
    with pytest.raises(BusError, match="exists"):
        keys.new(cfg)


def test_a_sealed_datagram_opens_once_and_its_replay_is_refused(tmp_path: Path) -> None:
    cfg = cfg_in(tmp_path)
    a, b = guard(cfg, "ms"), guard(cfg, "msched")
    data = a.seal(body())
    assert b.open(data, False, "x") == (body(), False)
    assert b.open(data, False, "x") is None and b.stats["dropped_replay"] == 1
    again = a.seal(body())  # a retransmission is sealed anew: not a replay
    assert b.open(again, False, "x") is not None


def test_a_counter_of_any_value_costs_constant_time_and_memory(tmp_path: Path) -> None:
    """A lot key holder's counter jumps by 2^62 (then to the top of 64 bits): each is taken in
    microseconds, the window is forgotten past WINDOW (not shifted 2^62 bits), and replays of the
    new high counter are still refused."""
    cfg = cfg_in(tmp_path)
    lot, module = guard(cfg, "lot:7"), guard(cfg, "msched")
    assert module.open(lot.seal(body("lot:7")), False, "x") is not None
    started = time.perf_counter()
    for counter in (2**62, 2**63, 2**64 - 2):
        lot._counters[0] = counter
        sealed = lot.seal(body("lot:7"))
        assert module.open(sealed, False, "x") is not None
        assert module.open(sealed, False, "x") is None  # its replay
    assert time.perf_counter() - started < 0.1
    (window,) = module._windows[auth.LOT].values()
    assert window[0] == 2**64 - 1 and window[1].bit_length() <= auth.WINDOW
    lot._counters[0] = 2**64 - 2 - auth.WINDOW  # sealed WINDOW behind the highest: just outside
    assert module.open(lot.seal(body("lot:7")), False, "x") is None
    assert module.stats["dropped_replay"] == 4


def test_forged_altered_and_foreign_datagrams_are_dropped_unread(tmp_path: Path) -> None:
    cfg = cfg_in(tmp_path / "one")
    other = cfg_in(tmp_path / "two")
    b = guard(cfg, "msched")
    sealed = guard(cfg, "ms").seal(body())
    assert b.open(body(), False, "x") is None  # no seal at all
    assert b.open(sealed[:-1] + bytes([sealed[-1] ^ 1]), False, "x") is None
    assert b.open(sealed[:20] + b"X" + sealed[21:], False, "x") is None
    assert b.open(guard(other, "ms").seal(body()), False, "x") is None
    assert b.open(sealed, True, "x") is None  # a bus-port datagram replayed onto the beat port
    assert b.stats["dropped_bad_mac"] == 2 and b.stats["dropped_wrong_channel"] == 1
    assert b.stats["dropped_other_cell"] + b.stats["dropped_short"] == 2


def test_a_lot_script_cannot_speak_as_a_module(tmp_path: Path) -> None:
    cfg = cfg_in(tmp_path)
    lot, module = guard(cfg, "lot:7"), guard(cfg, "msched")
    assert lot.role == "lot" and module.role == "module"
    assert module.open(lot.seal(body("lot:7")), False, "x") == (body("lot:7"), True)
    assert module.open(lot.seal(body("ms")), False, "x") is None  # the lot key signs for lot entities only
    assert module.stats["dropped_lot_key_misused"] == 1
    # A lot script reads the modules' traffic (their lot MAC) ...
    assert lot.open(guard(cfg, "ms").seal(body()), False, "x") == (body(), False)


def test_stale_and_pre_start_datagrams_are_replays(tmp_path: Path) -> None:
    cfg = cfg_in(tmp_path, replay_window=10.0, max_skew=1.0)
    a = guard(cfg, "ms")
    old = a.seal(body())
    b = guard(cfg, "msched")
    b._started += 5  # b started after `old` was sealed (more than max_skew later)
    assert b.open(old, False, "x") is None and b.stats["dropped_replay"] == 1
    b._started -= 5
    b.cfg = BusConfig(key_file=cfg.key_file, lot_key_file=cfg.lot_key_file, replay_window=-1.0)
    assert b.open(a.seal(body()), False, "x") is None and b.stats["dropped_stale"] == 1


def test_rotation_keeps_old_and_new_accepted_through_the_overlap(tmp_path: Path) -> None:
    cfg = cfg_in(tmp_path)
    old_sender = guard(cfg, "ms")
    receiver = guard(cfg, "msched")
    keys.rotate(cfg, overlap=60, take_up=3, now=time.time() - 10)  # new keys in use now
    new_sender = guard(cfg, "ms")
    assert new_sender.key_ids == (2, 2)
    receiver._mtime = 0
    receiver.refresh()
    assert receiver.open(old_sender.seal(body()), False, "x") is not None
    assert receiver.open(new_sender.seal(body(inc=6)), False, "x") is not None
    keys.rotate(cfg, overlap=4, take_up=3, now=time.time() - 100)  # key 2 expired long ago
    receiver._mtime = 0
    receiver.refresh()
    assert receiver.open(new_sender.seal(body(inc=6)), False, "x") is None
    assert receiver.stats["dropped_unknown_key"] == 1


def test_a_rotated_key_is_taken_up_at_its_time_without_the_file_changing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The heartbeat's refresh rebuilds the keyed MACs only when something changed: the file, or a
    key's send_from/until passing (then without any change to the file)."""
    cfg = cfg_in(tmp_path)
    now = time.time()
    keys.rotate(cfg, overlap=60, take_up=3, now=now)
    sender = guard(cfg, "ms")
    assert sender.key_ids == (1, 1)  # the new keys are not used before their take-up
    macs = sender._macs
    sender.refresh()
    assert sender._macs is macs and sender.key_ids == (1, 1)  # nothing changed: nothing rebuilt
    monkeypatch.setattr(auth.time, "time", lambda: now + 4)
    sender.refresh()
    assert sender.key_ids == (2, 2)


def test_drops_are_summarised_per_source_not_logged_each(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    b = guard(cfg_in(tmp_path), "msched")
    with caplog.at_level(logging.WARNING):
        for i in range(1000):
            b.open(b"garbage" * 20, False, ("10.0.0.9", 4000 + i % 2))
        assert not caplog.records  # nothing per datagram
        b.drops.report(100.0)  # the next heartbeat: one line per source
        for i in range(1000):
            b.open(b"garbage" * 20, False, ("10.0.0.9", 4000 + i % 2))
        b.drops.report(105.0)  # within the interval: nothing more
        assert len(caplog.records) == 2 and "500 other cell" in caplog.text
        b.drops.report(110.0)
    assert len(caplog.records) == 4


@pytest.mark.parametrize(
    "bad",
    [
        b'{"n":NaN}',
        b'{"n":1e999}',
        b'{"n":-Infinity}',
    ],
)
def test_the_wire_refuses_nan_and_infinity(bad: bytes) -> None:
    good = wire.encode(wire.Envelope(kind="msg", src="a", inc=1, seq=1, conv="a.1.1", cls="PING", msg="Ping"))
    with pytest.raises(MessageError):
        wire.decode(good + bad)


def test_the_wire_refuses_nul_and_over_long_names() -> None:
    with pytest.raises(MessageError, match="NUL"):
        wire.decode(wire.encode(wire.Envelope(kind="hello", src="w\0c", inc=1)))
    hello = wire.encode(wire.Envelope(kind="hello", src="wc", inc=1, interest=("X" * 200,)))
    with pytest.raises(MessageError, match="interest"):  # the encoder refuses it; a hostile sender need not
        wire.decode(hello[:-202] + bytes([201]) + b"X" * 201 + b"\0")  # (the entry's subject: none)
    with pytest.raises(MessageError, match="NUL"):
        catalogue.check("GET_STATUS", "Get_Status", {"machine_id": "wc1\0"})
    with pytest.raises(MessageError, match="over 200"):
        catalogue.check("GET_STATUS", "Get_Status", {"machine_id": "m" * 201})
    catalogue.check("CELL_EVENT", "Cell_Event", {"text": "t" * 1000})  # free text may be long


def test_refusal_answers_with_the_class_ack_message() -> None:
    answer = catalogue.refusal("SHUTDOWN", AckCode.NOT_AUTH, "no")
    assert answer is not None and answer.name == "Shutdown_Ack" and answer.ack_code == "Not_Auth"
    assert catalogue.refusal("UPD_ME_ST", AckCode.NOT_AUTH, "no") is None  # a broadcast: nothing to answer
    assert auth.SEAL_BYTES == 61


def test_the_lot_classes_are_the_conversations_the_lot_library_starts() -> None:
    """The lot key's rights are what a lot entity needs: every class the library opens, nothing more."""
    source = "".join(p.read_text() for p in (Path(__file__).parents[2] / "gwc" / "lot").glob("*.py"))
    started = {c for c in catalogue.CONVERSATION_CLASSES if f'"{c}"' in source or f"Conv.{c}" in source}
    started -= {"RUN_COMPL", "UPD_ME_ST", "MOD_DIED", "LOT_MOVED"}  # listened to, never sent
    assert started == catalogue.LOT_CLASSES


def test_gwc_key_commands_make_show_and_rotate_without_printing_secrets(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = make_config(tmp_path, None)  # a private cell: its keys made at set-up
    monkeypatch.setenv("GWC_CONFIG", str(cfg.path))
    runner = CliRunner()
    _, keyset = keys.load(cfg.bus, "module")
    again = runner.invoke(cli, ["key", "new"])
    assert again.exit_code != 0 and "exists" in again.output  # never replaced by accident
    assert runner.invoke(cli, ["key", "rotate", "--overlap", "2"]).exit_code != 0  # shorter than the take-up
    assert runner.invoke(cli, ["key", "rotate", "--take-up", "3", "--overlap", "30"]).exit_code == 0
    shown = runner.invoke(cli, ["key", "show", "--json"])
    assert shown.exit_code == 0 and len(json.loads(shown.output)) == 4
    assert all(k.secret.hex() not in shown.output for k in keys.load(cfg.bus, "module")[1].keys)
    assert keys.load(cfg.bus, "module")[1].cell_id == keyset.cell_id


def test_key_rotate_keeps_each_key_files_mode_and_group(tmp_path: Path) -> None:
    cfg = cfg_in(tmp_path)
    lot = tmp_path / "lot.key"
    group = 65534 if os.geteuid() == 0 else os.getegid()  # nogroup: a group of lot scripts' own
    os.chown(lot, -1, group)
    lot.chmod(0o640)  # as docs/security.md asks for scripts run as another user
    keys.rotate(cfg, overlap=10, take_up=3)
    assert (stat.S_IMODE(lot.stat().st_mode), lot.stat().st_gid) == (0o640, group)
    assert stat.S_IMODE((tmp_path / "cell.key").stat().st_mode) == 0o600
    lot.chmod(0o666)  # never made readable by others, whatever it was
    keys.rotate(cfg, overlap=10, take_up=3)
    assert stat.S_IMODE(lot.stat().st_mode) == 0o660
