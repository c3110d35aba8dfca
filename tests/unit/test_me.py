"""The machine sides (dummy ME, CMM ME over a pty to the simulator) and the WC's queue end, without the bus.

Each ME runs its real loop in a thread on real queues; the test plays the WC with a Channel.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import re
import shutil
import socket
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from gwc.config import Config
from gwc.errors import ConfigError, QueueError, QueueTimeout
from gwc.files import previous
from gwc.ipc.codes import AckCode
from gwc.ipc.mq import MAX_MESSAGES, Channel, MeMessage, MessageId, remove_queues
from gwc.me import make_machine
from gwc.me.cmm_sim import CmmSimulator, fault_file, inject_fault, sim_link
from gwc.me.line import Garbage, LineTimeout, RecordStream
from gwc.me.machine import RUN_NO_FILE, MachineSide
from gwc.me.results import read_outcome, read_results, write_results
from gwc.wc.link import MeDied, MeLink
from tests.harness import wait_for, write_cell_config

LOG = logging.getLogger("test_me")
LOG.setLevel(5)


class Running:
    """A started ME (and simulator) in threads, with the WC's end of its queues."""

    def __init__(self, cfg: Config, machine: str) -> None:
        self.cfg = cfg
        self.machine = machine
        self.stop = threading.Event()
        self.threads: list[threading.Thread] = []
        self.wc = Channel(cfg.ipc_prefix, machine, "wc", LOG).open()
        self.seq = 0
        self.me: MachineSide | None = None

    def run(self, target: Callable[[threading.Event], int]) -> None:
        t = threading.Thread(target=target, args=(self.stop,), daemon=True)
        t.start()
        self.threads.append(t)

    def ask(self, mid: MessageId, timeout: float = 10, **fields: Any) -> MeMessage:
        self.seq += 1
        self.wc.send(MeMessage(mid, seq=self.seq, **fields))
        answer = self.wc.receive(timeout)
        assert answer.seq == self.seq, answer
        return answer

    def halt(self) -> None:
        """Stop the threads. In its own process a signal ends the ME's wait for a request; in a thread a
        request does (its answer, seq 0, is stale to whoever reads the WC's queue)."""
        self.stop.set()
        waker = Channel(self.cfg.ipc_prefix, self.machine, "wc", LOG).open()
        with contextlib.suppress(QueueError):
            waker.send(MeMessage(MessageId.NO_MESSAGE, seq=0))
        waker.close()
        for t in self.threads:
            t.join(5)

    def close(self) -> None:
        self.halt()
        self.wc.close()
        remove_queues(self.cfg.ipc_prefix, [self.machine])


@pytest.fixture
def machine(tmp_path: Path) -> Iterator[Callable[..., Running]]:
    made: list[Running] = []

    def make(**options: Any) -> Running:
        spec = {"id": f"m{uuid.uuid4().hex[:6]}", **options}
        cfg = write_cell_config(tmp_path / f"var{len(made)}", None, machines=[spec])
        r = Running(cfg, spec["id"])
        made.append(r)
        if spec.get("kind") == "cmm":
            r.run(CmmSimulator(cfg, cfg.machine(r.machine), LOG).serve)
            if spec["serial"]["port"] == "sim":
                wait_for(lambda: sim_link(cfg, r.machine).exists(), 10, "the simulator's pty link")
            if "listen" in spec.get("sim", {}):  # else the ME's first open may come before the bind, and be refused
                port = int(spec["sim"]["listen"].rpartition(":")[2])
                wait_for(lambda: listening(port), 10, f"the simulator's device server on port {port}")
        r.me = make_machine(cfg, r.machine, LOG)
        r.run(r.me.serve)
        return r

    yield make
    for r in made:
        r.close()


def recipe(tmp_path: Path, text: str = "# recipe\nRUN\n") -> str:
    path = tmp_path / "recipe.v1"
    path.write_text(text)
    return str(path)


def start_and_setup(m: Running, tmp_path: Path) -> None:
    assert m.ask(MessageId.ME_START).ack_code == AckCode.ACK_OK
    assert m.ask(MessageId.SETUP_RUN, file_name=recipe(tmp_path), recipe_id="dummy_recipe").ack_code == AckCode.ACK_OK


# ----------------------------------------------------------------------------- dummy ME


def test_dummy_runs_a_recipe_and_reports_results(machine, tmp_path: Path) -> None:
    m = machine(kind="dummy", run_time=0.2, results={"DIAMETER": "25.02"})
    start_and_setup(m, tmp_path)
    out = tmp_path / "results" / "run-1.txt"
    assert m.ask(MessageId.START_RUN, file_name=str(out), recipe_id="dummy_recipe").ack_code == AckCode.ACK_OK
    pings = 0
    while True:  # the ME answers pings while its run goes on
        m.seq += 1
        m.wc.send(MeMessage(MessageId.NO_MESSAGE, seq=m.seq))
        msg = m.wc.receive(5)
        if msg.message_id == MessageId.RUN_COMPL:
            break
        assert (msg.message_id, msg.ack_code) == (MessageId.NO_MESSAGE, AckCode.ACK_OK)
        # a restarted WC learns from the ping whether the run it resumes is still going
        assert (msg.alarm_text, msg.file_name, msg.recipe_id) == ("running", str(out), "dummy_recipe")
        pings += 1
        time.sleep(0.02)
    assert pings >= 3
    assert msg.ack_code == AckCode.ACK_OK and msg.file_name == str(out)
    results = read_results(out)
    assert results["RESULT"] == "PASS" and results["RECIPE"] == "dummy_recipe" and results["DIAMETER"] == "25.02"
    assert float(results["RUN_TIME"]) >= 0.2
    assert read_outcome(out) == ("ACK_OK", "")  # how the run ended, for a WC that lost its RUN_COMPL
    idle = m.wc.receive(5)  # the answer to the last ping, sent after RUN_COMPL
    assert (idle.seq, idle.ack_code, idle.alarm_text, idle.file_name) == (m.seq, AckCode.ACK_OK, "idle", "")


def test_dummy_homing_alarm_holds_the_start_until_cleared(machine) -> None:
    m = machine(kind="dummy", homing_alarm=True)
    m.wc.send(MeMessage(MessageId.ME_START, seq=41))
    alarm = m.wc.receive(5)
    assert (alarm.message_id, alarm.alarm_text) == (MessageId.CELL_ALAR, "HOME_CMM")
    with pytest.raises(QueueTimeout):
        m.wc.receive(0.3)  # nothing until the operator has cleared the alarm
    m.wc.send(MeMessage(MessageId.ME_START_WAIT, ack_code=AckCode.ACK_OK, alarm_text="HOME_CMM"))
    ready = m.wc.receive(5)
    assert (ready.message_id, ready.seq, ready.ack_code) == (MessageId.ME_START, 41, AckCode.ACK_OK)


def test_dummy_start_cancelled_while_homing_stays_shut_down_and_a_late_clear_does_nothing(machine) -> None:
    m = machine(kind="dummy", homing_alarm=True)
    m.wc.send(MeMessage(MessageId.ME_START, seq=42))
    assert m.wc.receive(5).message_id == MessageId.CELL_ALAR
    m.wc.send(MeMessage(MessageId.ME_START_WAIT, ack_code=AckCode.REQ_CANCEL, alarm_text="HOME_CMM"))
    cancelled = m.wc.receive(5)
    assert (cancelled.message_id, cancelled.seq, cancelled.ack_code) == (MessageId.ME_START, 42, AckCode.REQ_CANCEL)
    assert "cancelled" in cancelled.alarm_text
    m.wc.send(MeMessage(MessageId.ME_START_WAIT, ack_code=AckCode.ACK_OK, alarm_text="HOME_CMM"))  # a late clear
    assert m.ask(MessageId.NO_MESSAGE).ack_code == AckCode.NOTNOW  # still shut down, not homed


def test_dummy_refuses_what_its_state_does_not_allow(machine, tmp_path: Path) -> None:
    m = machine(kind="dummy")
    assert m.ask(MessageId.NO_MESSAGE).ack_code == AckCode.NOTNOW  # shut down: a WC learns the ME restarted
    assert m.ask(MessageId.SETUP_RUN, file_name=recipe(tmp_path), recipe_id="r").ack_code == AckCode.NOTNOW
    assert m.ask(MessageId.ME_START).ack_code == AckCode.ACK_OK
    assert m.ask(MessageId.NO_MESSAGE).ack_code == AckCode.ACK_OK
    assert m.ask(MessageId.START_RUN, file_name="/tmp/x").ack_code == AckCode.NOTNOW  # not set up
    missing = m.ask(MessageId.SETUP_RUN, file_name=str(tmp_path / "nope"), recipe_id="r")
    assert missing.ack_code == AckCode.REC_INVAL and missing.alarm_text.startswith("recipe file")
    bad = m.ask(MessageId.RUN_COMPL)
    assert bad.ack_code == AckCode.BAD_MESSAGE
    shut = m.ask(MessageId.ME_SHUT)
    assert (shut.message_id, shut.ack_code) == (MessageId.ME_SHUT_C, AckCode.ACK_OK)


def test_dummy_configured_to_fail_a_run_and_to_fail_homing(machine, tmp_path: Path) -> None:
    m = machine(kind="dummy", run_time=0.0, fail_runs=[2])
    start_and_setup(m, tmp_path)
    codes = []
    for n in (1, 2, 3):
        assert m.ask(MessageId.START_RUN, file_name=str(tmp_path / f"r{n}")).ack_code == AckCode.ACK_OK
        done = m.wc.receive(5)
        codes.append((done.message_id, done.ack_code, read_results(done.file_name)["RESULT"]))
        assert read_outcome(done.file_name) == (
            (AckCode.RUN_FAIL, "configured to fail") if n == 2 else (AckCode.ACK_OK, "")
        )
        m.ask(MessageId.SETUP_RUN, file_name=recipe(tmp_path), recipe_id="dummy_recipe")
    assert codes == [
        (MessageId.RUN_COMPL, AckCode.ACK_OK, "PASS"),
        (MessageId.RUN_COMPL, AckCode.RUN_FAIL, "FAIL"),
        (MessageId.RUN_COMPL, AckCode.ACK_OK, "PASS"),
    ]
    f = machine(kind="dummy", fail_start=True)
    assert f.ask(MessageId.ME_START).ack_code == AckCode.START_FAIL


def test_dummy_keeps_answers_while_the_wc_is_away(machine, tmp_path: Path) -> None:
    m = machine(kind="dummy", run_time=0.0)
    start_and_setup(m, tmp_path)
    for i in range(MAX_MESSAGES - 1):  # fill the WC's queue but one slot
        m.wc.send(MeMessage(MessageId.NO_MESSAGE, seq=1000 + i))
    wait_for(lambda: m.wc.pending()[1] == MAX_MESSAGES - 1, 5, "ping answers queued")
    m.wc.send(MeMessage(MessageId.START_RUN, seq=2000, file_name=str(tmp_path / "r")))
    assert m.me is not None
    wait_for(lambda: m.me.waiting == 1, 5, "RUN_COMPL kept in the ME's outbox (START_RUN's answer took the last slot)")
    got = [m.wc.receive(5) for _ in range(MAX_MESSAGES + 1)]
    assert got[-2].seq == 2000 and got[-1].message_id == MessageId.RUN_COMPL


def test_bad_options_are_a_config_error(tmp_path: Path) -> None:
    cfg = write_cell_config(tmp_path, None, machines=[{"id": "x", "kind": "dummy", "run_time": "slow"}])
    with pytest.raises(ConfigError, match="run_time"):
        make_machine(cfg, "x", LOG)


# ----------------------------------------------------------------------------- CMM over a pty


CMM = {"kind": "cmm", "homing_alarm": False, "serial": {"port": "sim", "baudrate": 9600, "timeout": 5.0}}


def test_cmm_measures_parts_pass_and_fail_over_the_pty(machine, tmp_path: Path) -> None:
    m = machine(**CMM, sim={"measure_time": 0.1, "pattern": "PF"})
    assert m.ask(MessageId.ME_START).ack_code == AckCode.ACK_OK
    verdicts = []
    for n in (1, 2):
        assert (
            m.ask(MessageId.SETUP_RUN, file_name=recipe(tmp_path, "PART alum\n"), recipe_id="alum_chess_set").ack_code
            == AckCode.ACK_OK
        )
        out = tmp_path / f"cmm-{n}.txt"
        assert m.ask(MessageId.START_RUN, file_name=str(out)).ack_code == AckCode.ACK_OK
        done = m.wc.receive(5)
        assert (done.message_id, done.ack_code) == (MessageId.RUN_COMPL, AckCode.ACK_OK)
        verdicts.append(read_results(out)["RESULT"])
    assert verdicts == ["PASS", "FAIL"]


def test_cmm_download_then_upload_round_trips_the_program(machine, tmp_path: Path) -> None:
    m = machine(**CMM, sim={"measure_time": 0.0})
    assert m.ask(MessageId.ME_START).ack_code == AckCode.ACK_OK
    text = "PART king\nMEASURE all!\n" * 50  # '!' inside a program is payload, not a record end
    assert m.ask(MessageId.DNLD_ME, file_name=recipe(tmp_path, text), recipe_id="king").ack_code == AckCode.ACK_OK
    up = m.ask(MessageId.UPLD_ME, recipe_id="king")
    assert up.ack_code == AckCode.ACK_OK and Path(up.file_name).read_text() == text
    assert m.ask(MessageId.UPLD_ME, recipe_id="queen").ack_code == AckCode.REC_INVAL


def test_cmm_without_its_simulator_fails_to_start(tmp_path: Path) -> None:
    cfg = write_cell_config(tmp_path, None, machines=[{"id": "c", **CMM, "serial": {"port": "sim", "timeout": 0.3}}])
    r = Running(cfg, "c")
    try:
        r.run(make_machine(cfg, "c", LOG).serve)
        answer = r.ask(MessageId.ME_START)
        assert answer.ack_code == AckCode.START_FAIL and "simulator" in answer.alarm_text
    finally:
        r.close()


def test_record_stream_refuses_garbage_shown_escaped() -> None:
    chunks = [b"\x00\xfePASS!", b"x" * 200]
    stream = RecordStream(lambda t: chunks.pop() if chunks else b"", lambda b: None, "test line")
    with pytest.raises(Garbage, match="without '!'"):
        stream.read_record(0.1)
    with pytest.raises(Garbage, match=r"not a record: \\x00\\xfePASS!"):
        stream.read_record(0.1)
    with pytest.raises(LineTimeout, match="within"):
        stream.read_record(0.05)


def test_record_stream_takes_listing_9s_verdict_without_its_bang() -> None:
    chunks = [b"FAIL", b"PASSREADY!"]
    stream = RecordStream(lambda t: chunks.pop() if chunks else b"", lambda b: None, "test line")
    assert stream.next_record(1, bare_verdict=True) == "PASS!"  # unambiguous: another record follows
    assert stream.next_record(1, bare_verdict=True) == "READY!"
    assert stream.next_record(1, bare_verdict=True) == "FAIL!"  # unambiguous: the line went quiet
    assert stream.next_record(0.1, bare_verdict=True) is None


def listening(port: int) -> bool:
    """Whether a socket listens on TCP port (read from /proc: connecting would take the one ME's place)."""
    rows = (row.split() for row in Path("/proc/net/tcp").read_text().splitlines()[1:])
    return any(r[1].endswith(f":{port:04X}") and r[3] == "0A" for r in rows)  # 0A: LISTEN


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def cmm_on(transport: str, line_timeout: float = 0.5, **options: Any) -> dict[str, Any]:
    """A CMM machine whose simulator is on a pty, or a serial device server on TCP (socket:// or rfc2217://).
    The line's timeout is short, so that the fault tests find a silent CMM soon."""
    serial = {"port": "sim", "timeout": line_timeout}
    sim = {"measure_time": 0.05, **options.pop("sim", {})}
    if transport != "pty":
        port = free_port()
        serial["port"] = f"{transport}://127.0.0.1:{port}"
        sim["listen"] = f"127.0.0.1:{port}"
    return {**CMM, "serial": serial, "sim": sim, "run_timeout": 1.5, "reprobe_max": 0.3, **options}


def next_from_me(m: Running, timeout: float = 10) -> MeMessage:
    """The next record the ME sends on its own (answers to nothing)."""
    return m.wc.receive(timeout)


def setup_and_start(m: Running, tmp_path: Path, n: int) -> Path:
    rec = recipe(tmp_path, "PART alum\n")
    answer = m.ask(MessageId.SETUP_RUN, file_name=rec, recipe_id="alum_chess_set")
    assert answer.ack_code == AckCode.ACK_OK, answer
    out = tmp_path / f"run-{n}.txt"
    assert m.ask(MessageId.START_RUN, file_name=str(out)).ack_code == AckCode.ACK_OK
    return out


TRANSPORTS = ["pty", "socket", "rfc2217"]


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_cmm_power_cycled_while_idle_is_lost_then_back_and_measures(machine, tmp_path: Path, transport: str) -> None:
    m = machine(**cmm_on(transport))
    assert m.ask(MessageId.ME_START).ack_code == AckCode.ACK_OK
    inject_fault(m.cfg, m.machine, "power_cycle", **{"for": 0.5})
    lost = next_from_me(m)
    assert lost.message_id == MessageId.ME_LOST, lost
    refused = m.ask(MessageId.SETUP_RUN, file_name=recipe(tmp_path), recipe_id="alum_chess_set")
    assert refused.ack_code == AckCode.NOTNOW and "does not answer" in refused.alarm_text
    assert next_from_me(m).message_id == MessageId.ME_BACK
    out = setup_and_start(m, tmp_path, 1)  # the program is downloaded again: the CMM forgot it
    done = next_from_me(m)
    assert (done.message_id, done.ack_code) == (MessageId.RUN_COMPL, AckCode.ACK_OK)
    assert read_results(out)["RESULT"] == "PASS"


@pytest.mark.parametrize(
    ("fault", "params", "note", "lost"),
    [
        ("power_cycle", {"for": 0.5}, "line lost during the run", True),
        ("garbage", {"kind": "binary"}, r"garbage during the run: .*not a record: \\x00\\xfe\\x13PA\\x81SS!", False),
    ],
)
def test_cmm_fault_during_a_run_fails_the_run_with_its_reason(
    machine, tmp_path: Path, fault: str, params: dict[str, Any], note: str, lost: bool
) -> None:
    m = machine(**cmm_on("pty", sim={"measure_time": 0.6}))
    assert m.ask(MessageId.ME_START).ack_code == AckCode.ACK_OK
    if fault == "garbage":  # instead of the next verdict
        inject_fault(m.cfg, m.machine, fault, **params)
        wait_for(lambda: not fault_file(m.cfg, m.machine).exists(), 5, "the simulator to take the fault")
    out = setup_and_start(m, tmp_path, 1)
    if fault != "garbage":  # while the part is measured
        inject_fault(m.cfg, m.machine, fault, **params)
    done = next_from_me(m)
    assert (done.message_id, done.ack_code) == (MessageId.RUN_COMPL, AckCode.RUN_FAIL), done
    assert read_results(out)["RESULT"] == "NONE"
    assert re.search(note, read_outcome(out)[1]), read_outcome(out)
    if lost:
        assert next_from_me(m).message_id == MessageId.ME_LOST
        assert next_from_me(m).message_id == MessageId.ME_BACK
    out = setup_and_start(m, tmp_path, 2)
    done = next_from_me(m)
    assert (done.message_id, done.ack_code) == (MessageId.RUN_COMPL, AckCode.ACK_OK), done
    assert read_results(out)["RUN_NO"] == "2"


def test_cmm_silent_at_a_setup_refuses_it_notnow_is_lost_then_back(machine, tmp_path: Path) -> None:
    m = machine(**cmm_on("pty"))
    assert m.ask(MessageId.ME_START).ack_code == AckCode.ACK_OK
    inject_fault(m.cfg, m.machine, "silent", **{"for": 1.5})
    wait_for(lambda: not fault_file(m.cfg, m.machine).exists(), 5, "the simulator to take the fault")
    m.wc.send(MeMessage(MessageId.SETUP_RUN, seq=77, file_name=recipe(tmp_path), recipe_id="alum_chess_set"))
    lost, refused = next_from_me(m), next_from_me(m)  # the WC hears the machine is lost, then the refusal
    assert lost.message_id == MessageId.ME_LOST and "did not answer STATUS" in lost.alarm_text
    assert (refused.seq, refused.ack_code) == (77, AckCode.NOTNOW)  # a lot takes Notnow as: ask again
    assert next_from_me(m).message_id == MessageId.ME_BACK
    out = setup_and_start(m, tmp_path, 1)
    assert next_from_me(m).ack_code == AckCode.ACK_OK and read_results(out)["RESULT"] == "PASS"


@pytest.mark.skipif(shutil.which("gkermit") is None, reason="gkermit is not installed (bin/setup installs it as root)")
@pytest.mark.parametrize("transport", ["socket", "rfc2217"])  # RFC 2217 doubles Kermit's 0xFF bytes (Telnet's IAC)
def test_cmm_in_thesis_mode_kermit_transfer_and_a_verdict_without_bang(machine, tmp_path: Path, transport: str) -> None:
    # No fault here: a longer line timeout, so that the homing's resync is not refused on a loaded machine
    # (four test workers on two cores, the RFC 2217 server starting up beside two Kermit transfers).
    m = machine(**cmm_on(transport, line_timeout=3.0, transfer="kermit", sim={"bang": False, "pattern": "PF"}))
    assert m.ask(MessageId.ME_START).ack_code == AckCode.ACK_OK
    verdicts = []
    for n in (1, 2):
        out = setup_and_start(m, tmp_path, n)
        done = next_from_me(m)
        assert done.ack_code == AckCode.ACK_OK, done
        verdicts.append(read_results(out)["RESULT"])
    assert verdicts == ["PASS", "FAIL"]
    text = "PART king\nMEASURE all!\n" * 50
    assert m.ask(MessageId.DNLD_ME, file_name=recipe(tmp_path, text), recipe_id="king").ack_code == AckCode.ACK_OK
    up = m.ask(MessageId.UPLD_ME, recipe_id="king")
    assert up.ack_code == AckCode.ACK_OK and Path(up.file_name).read_text() == text


def test_cmm_probing_a_device_server_that_holds_the_open_still_answers_the_wcs_pings(machine, tmp_path: Path) -> None:
    """While the CMM is lost, a server on its port accepts and says nothing: pyserial's rfc2217 open
    waits 3 s for the Telnet negotiation (a switched-off host's TCP connect, up to 5 s). The ME opens in
    the background: its pings are answered at once meanwhile (the WC takes an ME silent 1.5 s for dead)."""
    m = machine(**cmm_on("rfc2217"))
    assert m.ask(MessageId.ME_START).ack_code == AckCode.ACK_OK
    inject_fault(m.cfg, m.machine, "hangup", **{"for": 6.0})  # the simulator's listener closed for 6 s
    assert next_from_me(m).message_id == MessageId.ME_LOST
    port = int(m.cfg.machine(m.machine).options["sim"]["listen"].rpartition(":")[2])
    pings = 0
    with socket.socket() as mute:
        mute.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        mute.bind(("127.0.0.1", port))
        mute.listen(1)
        mute.settimeout(5)
        conn, _ = mute.accept()  # the ME's probe: accepted, never answered
        with conn:
            conn.settimeout(0.1)
            deadline = time.monotonic() + 5
            while time.monotonic() < deadline:  # until the ME gives the open up and hangs up
                began = time.monotonic()
                assert m.ask(MessageId.NO_MESSAGE, timeout=1.0).ack_code == AckCode.ACK_OK
                assert time.monotonic() - began < 0.5
                pings += 1
                try:
                    if conn.recv(100) == b"":
                        break
                except TimeoutError:
                    pass
            else:
                raise AssertionError("the ME never gave up the open of a mute server")
    assert pings >= 10  # answered all along the ~3 s the open was held
    assert next_from_me(m, timeout=15).message_id == MessageId.ME_BACK  # the simulator's listener is back
    out = setup_and_start(m, tmp_path, 1)
    assert next_from_me(m).ack_code == AckCode.ACK_OK and read_results(out)["RESULT"] == "PASS"


def test_run_numbers_go_on_across_me_restarts(machine, tmp_path: Path) -> None:
    m = machine(kind="dummy", run_time=0.0)
    start_and_setup(m, tmp_path)
    assert m.ask(MessageId.START_RUN, file_name=str(tmp_path / "r1")).ack_code == AckCode.ACK_OK
    assert read_results(next_from_me(m).file_name)["RUN_NO"] == "1"
    again = make_machine(m.cfg, m.machine, LOG)  # a new ME process of the same machine
    assert again.run_no == 1
    # Each run's number is written over the previous one's file and the two swapped (gwc.files.rewrite):
    # from the second run on, no file is made or replaced.
    run_no = again.memory / RUN_NO_FILE
    inodes = set()
    for n in (2, 3, 4):
        setup = m.ask(MessageId.SETUP_RUN, file_name=recipe(tmp_path), recipe_id="dummy_recipe")
        assert setup.ack_code == AckCode.ACK_OK
        assert m.ask(MessageId.START_RUN, file_name=str(tmp_path / f"r{n}")).ack_code == AckCode.ACK_OK
        assert read_results(next_from_me(m).file_name)["RUN_NO"] == str(n)
        inodes.add(run_no.stat().st_ino)
    assert run_no.read_text() == "4\n" and previous(run_no).read_text() == "3\n" and len(inodes) == 2


# ----------------------------------------------------------------------------- results file


def test_results_file_round_trip_and_errors(tmp_path: Path) -> None:
    path = write_results(tmp_path / "r.txt", {"A": "1", "NOTE": "two words"})
    assert read_results(path) == {"A": "1", "NOTE": "two words"}
    (tmp_path / "bad").write_text("A 1\nB\n")
    with pytest.raises(ValueError, match="line 2"):
        read_results(tmp_path / "bad")
    (tmp_path / "dup").write_text("A 1\n# c\n\nA 2\n")
    with pytest.raises(ValueError, match="twice"):
        read_results(tmp_path / "dup")
    with pytest.raises(ValueError):
        write_results(tmp_path / "x", {"TWO WORDS": "1"})
    assert read_outcome(path) is None  # a file with no recorded outcome
    path = write_results(tmp_path / "o.txt", {"RESULT": "FAIL"}, outcome=("Run_Fail", "the line\nwas lost"))
    assert read_results(path) == {"RESULT": "FAIL"}  # the outcome is a comment: never a result row
    assert read_outcome(path) == ("Run_Fail", "the line was lost")


# ----------------------------------------------------------------------------- the WC's end


def test_link_matches_answers_by_seq_and_declares_a_silent_me_dead(machine) -> None:
    m = machine(kind="dummy")
    m.wc.close()
    unsolicited: list[MeMessage] = []

    async def scenario() -> None:
        link = MeLink(Channel(m.cfg.ipc_prefix, m.machine, "wc", LOG), LOG, unsolicited.append)
        link.start(asyncio.get_running_loop())
        try:
            assert (await link.request(MeMessage(MessageId.ME_START), 5)).ack_code == AckCode.ACK_OK
            answers = await asyncio.gather(*(link.request(MeMessage(MessageId.NO_MESSAGE), 5) for _ in range(5)))
            assert len({a.seq for a in answers}) == 5
            m.halt()  # the ME stops answering
            with pytest.raises(MeDied, match="within 0.3s"):
                await link.request(MeMessage(MessageId.NO_MESSAGE), 0.3)
        finally:
            link.stop()

    asyncio.run(scenario())
    assert unsolicited == []


@pytest.mark.parametrize("delay", [0.0, 0.05], ids=["answer-at-once", "answer-after-the-quick-wait"])
def test_link_takes_its_answer_among_unsolicited_and_stale_records(tmp_path: Path, delay: float) -> None:
    """Whether the answer comes within MeLink's quick wait or later through the event loop, what the ME
    sends first (a RUN_COMPL of its own, a late answer to an older request) is handled as such."""
    prefix = f"/gwct.{uuid.uuid4().hex[:8]}"
    me = Channel(prefix, "m1", "me", LOG).open()
    unsolicited: list[MeMessage] = []

    def play_me() -> None:
        req = me.receive(5)
        time.sleep(delay)
        me.send(MeMessage(MessageId.RUN_COMPL, file_name="/tmp/r", ack_code=AckCode.ACK_OK))
        me.send(req.reply(AckCode.ACK_OK, alarm_text="late").with_seq(req.seq - 1 or 1))
        me.send(req.reply(AckCode.ACK_OK, alarm_text="idle"))

    async def scenario() -> MeMessage:
        link = MeLink(Channel(prefix, "m1", "wc", LOG), LOG, unsolicited.append)
        link.start(asyncio.get_running_loop())
        try:
            return await link.request(MeMessage(MessageId.NO_MESSAGE), 5)
        finally:
            link.stop()

    player = threading.Thread(target=play_me)
    player.start()
    try:
        answer = asyncio.run(scenario())
    finally:
        player.join(5)
        me.close()
        remove_queues(prefix, ["m1"])
    assert answer.alarm_text == "idle" and answer.ack_code == AckCode.ACK_OK
    assert [u.message_id for u in unsolicited] == [MessageId.RUN_COMPL]
