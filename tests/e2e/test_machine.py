"""The machine interface end to end (issue 4): WC and ME processes on real queues, the real bus, the
real database, and the servers they talk to (CAS, ERS, MS, MSCHED).

Every test drives the WC through its own conversations, as a lot entity and the operator do, and
clears alarms the operator's way (ALARM_CLR_REQ to the Cell Alarm Server).
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from typing import Any

import pytest

from gwc.ipc.bus import BlockingBus, BlockingConversation
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode
from gwc.ipc.mq import Channel, MessageId
from gwc.log import log_file_name
from tests.harness import CellHarness, wait_for

OK = AckCode.ACK_OK
T = 20.0  # generous deadlines: the machines are shared
SERVERS = ("cas", "ers", "ms", "msched")
CMM = {"id": "cmm_wc", "kind": "cmm", "serial": {"port": "sim", "baudrate": 9600, "timeout": 5.0}}


class Ear:
    """A bus attachment of the test's own that hears broadcasts (RUN_COMPL) as they come."""

    def __init__(self, cell: CellHarness, *classes: str) -> None:
        self.bus = BlockingBus(f"ear.{cell.tag}", cell.cfg.bus, cell.log, classes)
        self.heard: list[Message] = []

    def wait(self, what: str, match: Any, timeout: float = T) -> Message:
        deadline = time.monotonic() + timeout
        while True:
            for m in self.heard:
                if match(m):
                    self.heard.remove(m)
                    return m
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(f"timed out after {timeout:.0f}s waiting for {what} (heard {self.heard})")
            conv = self.bus.first_message(timeout=min(left, 0.5))
            if conv is not None:
                assert conv.first is not None
                self.heard.extend(conv.first.messages)
                conv.end()


@pytest.fixture
def machine_cell(make_cell: Any) -> Any:
    """machine_cell(*machines): servers up, each machine's processes up (machines Shutdown), an Ear."""
    ears: list[Ear] = []

    def make(*machines: dict[str, Any], prepare: str | None = None) -> tuple[CellHarness, Ear]:
        cell = make_cell(machines=list(machines))
        if prepare:  # test data the servers read at their start
            cell.query(prepare + " returning 1")
        cell.start_servers(*SERVERS)
        for m in machines:
            cell.start_machine_processes(m["id"])
        ears.append(Ear(cell, "RUN_COMPL"))
        return cell, ears[-1]

    yield make
    for e in ears:
        e.bus.close()


def ask(cell: CellHarness, cls: str, msg: Message, to: str) -> Message:
    conv, batch = cell.bus.request(cls, msg, to=to, timeout=T)
    conv.end()
    return batch.first


def status(cell: CellHarness, machine: str) -> tuple[Any, ...]:
    return cell.query(
        "select status, recipe_id, machine_run_id, start_time, end_time from machine_status where machine_id = %s",
        machine,
    )[0]


def accepts(cell: CellHarness, machine: str) -> list[str]:
    return [r[0] for r in cell.query("select op_type from accept_types where machine_id = %s order by 1", machine)]


def pending_alarm(cell: CellHarness, alarm_id: str, machine: str) -> int:
    rows = wait_for(
        lambda: cell.query(
            "select alarm_no from alarms where alarm_id = %s and machine_id = %s and cleared_at is null",
            alarm_id,
            machine,
        ),
        T,
        f"alarm {alarm_id} pending",
    )
    return int(rows[0][0])


def clear(cell: CellHarness, alarm_no: int) -> None:
    ack = ask(
        cell, "ALARM_CLR_REQ", message("Alarm_Clear_Request", alarm_no=alarm_no, cleared_by="test operator"), "cas"
    )
    assert ack.ack_code == OK, ack


def me_start(cell: CellHarness, machine: str) -> BlockingConversation:
    """Open ME_START; the WC acknowledges at once and answers ME_Ready when the machine is up."""
    conv, batch = cell.bus.request(
        "ME_START", message("Startup_Request", module=f"wc:{machine}"), to=f"wc:{machine}", timeout=T
    )
    assert batch.first.name == "Startup_Ack"
    if batch.first.ack_code != OK:
        conv.end()
        raise AssertionError(f"ME_START refused: {batch.first}")
    return conv


def ready(conv: BlockingConversation) -> Message:
    try:
        return conv.expect("ME_Ready", timeout=T).first
    finally:
        conv.end()


def start_machine(cell: CellHarness, machine: str, homing: bool) -> None:
    conv = me_start(cell, machine)
    if homing:
        clear(cell, pending_alarm(cell, "HOME_CMM", machine))
    done = ready(conv)
    assert done.ack_code == OK, done
    assert status(cell, machine)[0] == "Idle"


def setup_run(
    cell: CellHarness,
    machine: str,
    run_id: int,
    recipe: str | None = "dummy_recipe",
    op: str = "dummy_op",
    machine_id: str | None = None,
    start: bool = False,
) -> Message:
    return ask(
        cell,
        "SETUP_RUN",
        message(
            "Setup_Run",
            machine_id=machine_id or machine,
            recipe_id=recipe,
            op_type=op,
            machine_run_id=run_id,
            entity_id=1,
            start=start or None,
        ),
        f"wc:{machine}",
    )


def start_run(cell: CellHarness, machine: str, run_id: int) -> Message:
    return ask(cell, "START_RUN", message("Start_Run", machine_id=machine, machine_run_id=run_id), f"wc:{machine}")


def results(cell: CellHarness, machine: str, run_id: int) -> dict[str, str]:
    return dict(
        cell.query(
            "select param, value from machine_run_result where machine_id = %s and machine_run_id = %s", machine, run_id
        )
    )


def untold(cell: CellHarness, name: str, *steps: str) -> str | None:
    """What the log of `name` does not tell (yet) of these steps in this order; None if it tells them all."""
    text = cell.log_text(name)
    at = 0
    for step in steps:
        found = re.search(step, text[at:])
        if not found:
            return f"{log_file_name(name)} does not say {step!r} after position {at}"
        at += found.end()
    return None


def story(cell: CellHarness, name: str, *steps: str) -> None:
    """The log of `name` tells these steps in this order (by the time the story is waited for, a
    step's log line may still be on its way: the lines are waited for)."""
    try:
        wait_for(lambda: untold(cell, name, *steps) is None, T, "the story")
    except AssertionError:
        raise AssertionError(untold(cell, name, *steps)) from None


def gwc(cell: CellHarness, *args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "gwc", *args], env=cell.env(), capture_output=True, text=True, timeout=timeout
    )


# ----------------------------------------------------------------------------- the happy paths


def test_dummy_machine_homes_sets_up_runs_and_stores_its_results(machine_cell: Any) -> None:
    cell, ear = machine_cell(
        {"id": "wc3", "kind": "dummy", "run_time": 0.3, "homing_alarm": True, "results": {"DIAMETER": "25.02"}}
    )
    assert status(cell, "wc3")[0] == "Shutdown"
    conv = me_start(cell, "wc3")
    alarm = pending_alarm(cell, "HOME_CMM", "wc3")
    assert status(cell, "wc3")[0] == "Shutdown"  # the WC holds its startup until the operator clears it
    clear(cell, alarm)
    assert ready(conv).ack_code == OK
    assert status(cell, "wc3")[0] == "Idle"
    wait_for(lambda: accepts(cell, "wc3") == ["dummy_op", "measure", "mill_chess"], T, "accept types: all")

    set_up = setup_run(cell, "wc3", 9001, recipe=None)  # the machine's own recipe for the op type
    assert (set_up.ack_code, set_up.recipe_id) == (OK, "dummy_recipe")
    assert status(cell, "wc3")[:3] == ("Setup", "dummy_recipe", 9001)
    assert accepts(cell, "wc3") == []  # set up for a run: no other operation (Listing 3)
    assert start_run(cell, "wc3", 9001).ack_code == OK
    running = status(cell, "wc3")
    assert running[0] == "Running" and running[3] is not None  # start time

    done = ear.wait("Run_Complete of run 9001", lambda m: m.machine_run_id == 9001)
    assert (done.machine_id, done.ack_code) == ("wc3", OK)
    got = results(cell, "wc3", 9001)  # in the table before Run_Complete was sent
    assert got["RESULT"] == "PASS" and got["RECIPE"] == "dummy_recipe" and got["DIAMETER"] == "25.02"
    assert float(got["RUN_TIME"]) >= 0.3
    assert done.results == got  # small results ride with it, as stored: its lot need not read them
    wait_for(lambda: status(cell, "wc3")[0] == "Idle", T, "Idle again")
    assert status(cell, "wc3")[4] is not None  # end time
    wait_for(lambda: accepts(cell, "wc3") == ["dummy_op", "measure", "mill_chess"], T, "all operations again")
    assert not list((cell.cfg.results_dir / "wc3").glob("*")), "the results file is removed once loaded"

    story(
        cell,
        "wc:wc3",
        "ME_START to the ME",
        "the ME raises alarm HOME_CMM",
        rf"alarm {alarm} cleared",
        "Shutdown -> Idle",
        "accepts all its operations",
        "SETUP_RUN run 9001",
        "set up run 9001",
        "START_RUN run 9001",
        "Setup -> Running",
        "run 9001 started",
        "9001: 6 results stored",
        r"run 9001 complete \(ACK_OK\)",
    )
    # Asked together (docs/machine-interface.md, The order of a run's steps): in either order; the lot
    # is answered once the ME and the Machine Server have, and MSCHED's accepts-nothing is in place
    # before the run's end is told.
    story(cell, "wc:wc3", "SETUP_RUN run 9001", "Idle -> Setup", "set up run 9001")
    story(cell, "wc:wc3", "SETUP_RUN run 9001", "accept types: none", r"run 9001 complete \(ACK_OK\)")
    for step in ("Running -> Idle", "accept types: all"):
        story(cell, "wc:wc3", r"run 9001 complete \(ACK_OK\)", step)
    story(
        cell,
        "me:wc3",
        "homing: alarm HOME_CMM",
        "homing alarm cleared",
        r"machine ready \(Idle\)",
        "set up with recipe dummy_recipe",
        "run 1 started",
        "run 1 complete: ACK_OK",
    )
    shown = json.loads(gwc(cell, "machine", "status", "--json").stdout)
    assert {r["machine_id"]: (r["status"], r["wc"]) for r in shown} == {"wc3": ("Idle", "on bus")}


def test_cmm_over_a_pseudo_terminal_measures_a_pass_and_a_fail_part(machine_cell: Any) -> None:
    cell, ear = machine_cell({**CMM, "sim": {"measure_time": 0.2, "pattern": "PF"}})
    start_machine(cell, "cmm_wc", homing=True)  # the CMM always asks the operator to push its start button
    verdicts = []
    for run_id in (7001, 7002):
        assert setup_run(cell, "cmm_wc", run_id, "alum_chess_set", "alum_chess").ack_code == OK
        assert start_run(cell, "cmm_wc", run_id).ack_code == OK
        done = ear.wait(f"Run_Complete of run {run_id}", lambda m, r=run_id: m.machine_run_id == r)
        assert done.ack_code == OK  # a FAIL part is a run that worked: the verdict is in the results
        verdicts.append(results(cell, "cmm_wc", run_id)["RESULT"])
        wait_for(lambda: status(cell, "cmm_wc")[0] == "Idle", T, "Idle again")
    assert verdicts == ["PASS", "FAIL"]
    assert results(cell, "cmm_wc", 7001)["PART"] == "alum_chess_set"
    story(
        cell,
        "cmmsim:cmm_wc",
        "serial end published",
        "' DOWNLD !'",
        "part program alum_chess_set received",
        "'SETUP RUN !'",
        "part name: alum_chess_set",
        "'START RUN !'",
        "measured: PASS!",
        "'START RUN !'",
        "measured: FAIL!",
    )
    story(cell, "me:cmm_wc", "serial line to the CMM open", "the CMM answered PASS!", "the CMM answered FAIL!")


def test_a_stop_while_the_cmm_waits_to_be_homed_cancels_the_start_and_a_later_start_homes_again(
    machine_cell: Any,
) -> None:
    """Issue 41: `gwc machine stop` while `gwc machine start` waits for HOME_CMM cancels that start."""
    cell, _ = machine_cell({**CMM, "sim": {"measure_time": 0.2}})
    start = subprocess.Popen(
        [sys.executable, "-m", "gwc", "machine", "start", "cmm_wc"],
        env=cell.env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        homing = pending_alarm(cell, "HOME_CMM", "cmm_wc")
        stopped = gwc(cell, "machine", "stop", "cmm_wc")
        out, err = start.communicate(timeout=T)
    finally:
        if start.poll() is None:
            start.kill()
            start.wait()
    assert stopped.returncode == 0, stopped.stderr
    assert "wc:cmm_wc: shut down" in stopped.stdout, stopped.stdout
    # The start's conversation ends, failed, saying why.
    assert start.returncode != 0, out
    assert "REQ_CANCEL start cancelled" in err, err
    # The homing alarm was cleared by the cell as "start cancelled": nothing waits for it any more.
    cleared, by = cell.query("select cleared_at is not null, cleared_by from alarms where alarm_no = %s", homing)[0]
    assert cleared and by == "wc:cmm_wc: start cancelled", by
    late = ask(
        cell, "ALARM_CLR_REQ", message("Alarm_Clear_Request", alarm_no=homing, cleared_by="test operator"), "cas"
    )
    assert late.ack_code != OK and "already cleared" in (late.note or ""), late
    assert status(cell, "cmm_wc")[0] == "Shutdown" and accepts(cell, "cmm_wc") == []
    story(cell, "me:cmm_wc", "homing: alarm HOME_CMM", "start cancelled by the cell while waiting for homing")
    story(cell, "wc:cmm_wc", "the start is cancelled", f"alarm {homing} withdrawn", "not started: REQ_CANCEL")
    # The ME is shut down, not homed: a later start raises HOME_CMM again, and once homed the CMM is Idle.
    start_machine(cell, "cmm_wc", homing=True)
    again = cell.query("select alarm_no from alarms where machine_id = 'cmm_wc' and alarm_id = 'HOME_CMM'")
    assert len(again) == 2 and homing in {a for (a,) in again}
    assert accepts(cell, "cmm_wc") == ["alum_chess"]


# ----------------------------------------------------------------------------- the refusals


def test_requests_out_of_turn_get_the_thesis_answers_and_leave_the_machine_as_it_was(machine_cell: Any) -> None:
    cell, ear = machine_cell({"id": "wc1", "kind": "dummy", "run_time": 0.2})
    assert setup_run(cell, "wc1", 1).ack_code == AckCode.NOTNOW  # Shutdown: not started
    start_machine(cell, "wc1", homing=False)
    again = cell.bus.request("ME_START", message("Startup_Request", module="wc:wc1"), to="wc:wc1", timeout=T)
    again[0].end()
    assert again[1].first.ack_code == AckCode.NOTNOW  # only from Shutdown
    assert start_run(cell, "wc1", 1).ack_code == AckCode.NOTNOW  # not set up
    assert setup_run(cell, "wc1", 1, recipe="no_such_recipe").ack_code == AckCode.REC_INVAL
    assert setup_run(cell, "wc1", 1, op="alum_chess").ack_code == AckCode.REC_INVAL  # not this machine's op type
    assert setup_run(cell, "wc1", 1, machine_id="wc2").ack_code == AckCode.BAD_MESSAGE
    assert status(cell, "wc1")[0] == "Idle"

    down = ask(cell, "DNLD_ME", message("Download_Me", machine_id="wc1", recipe_id="dummy_recipe"), "wc:wc1")
    assert down.ack_code == OK
    up = ask(cell, "UPLD_ME", message("Upload_Me", machine_id="wc1", recipe_id="dummy_recipe"), "wc:wc1")
    assert up.ack_code == OK and up.version == 1  # the machine's copy is the approved version itself

    assert setup_run(cell, "wc1", 2).ack_code == OK
    assert setup_run(cell, "wc1", 3).ack_code == AckCode.NOTNOW  # Idle only
    assert (
        ask(cell, "UPLD_ME", message("Upload_Me", machine_id="wc1", recipe_id="dummy_recipe"), "wc:wc1").ack_code
        == AckCode.NOTNOW
    )
    assert start_run(cell, "wc1", 3).ack_code == AckCode.START_FAIL  # set up for run 2, not 3
    assert status(cell, "wc1")[:3] == ("Setup", "dummy_recipe", 2)
    assert start_run(cell, "wc1", 2).ack_code == OK
    ear.wait("Run_Complete of run 2", lambda m: m.machine_run_id == 2)
    wait_for(lambda: status(cell, "wc1")[0] == "Idle", T, "Idle again")


def test_failed_run_is_reported_run_fail_with_an_alarm_and_the_operator_stops_the_machine(machine_cell: Any) -> None:
    cell, ear = machine_cell({"id": "wc2", "kind": "dummy", "run_time": 0.1, "fail_runs": [1]})
    start_machine(cell, "wc2", homing=False)
    assert setup_run(cell, "wc2", 11).ack_code == OK
    assert start_run(cell, "wc2", 11).ack_code == OK
    assert ear.wait("Run_Complete of run 11", lambda m: m.machine_run_id == 11).ack_code == AckCode.RUN_FAIL
    assert results(cell, "wc2", 11)["RESULT"] == "FAIL"
    pending_alarm(cell, "RUN_FAIL", "wc2")
    wait_for(lambda: status(cell, "wc2")[0] == "Idle", T, "Idle again")
    assert setup_run(cell, "wc2", 12).ack_code == OK
    assert start_run(cell, "wc2", 12).ack_code == OK
    assert ear.wait("Run_Complete of run 12", lambda m: m.machine_run_id == 12).ack_code == OK

    # the operator takes the machine out of the cell from the command line
    wait_for(lambda: status(cell, "wc2")[0] == "Idle", T, "Idle again")
    stop = gwc(cell, "machine", "stop", "wc2")
    assert stop.returncode == 0 and "wc:wc2: shut down" in stop.stdout, stop.stderr
    assert status(cell, "wc2")[0] == "Shutdown" and accepts(cell, "wc2") == []
    table = gwc(cell, "machine", "status")
    assert re.search(r"^wc2\s+dummy\s+Shutdown\s", table.stdout, re.M), table.stdout
    unknown = gwc(cell, "machine", "start", "nope")
    assert unknown.returncode == 2 and "unknown machine 'nope'" in unknown.stderr, unknown.stderr


def test_shutdown_during_setup_and_during_a_run_waits_for_the_run(machine_cell: Any) -> None:
    cell, ear = machine_cell({"id": "wc4", "kind": "dummy", "run_time": 1.0})

    def shut() -> Message:
        conv, batch = cell.bus.request("ME_SHUT", message("Shutdown_Request", module="wc:wc4"), to="wc:wc4", timeout=T)
        try:
            assert batch.first.ack_code == OK, batch.first
            return conv.expect("ME_Stopped", timeout=T).first
        finally:
            conv.end()

    # Running -> Run_Shut -> (run completes) -> Shutdown
    start_machine(cell, "wc4", homing=False)
    assert setup_run(cell, "wc4", 21).ack_code == OK
    assert start_run(cell, "wc4", 21).ack_code == OK
    stopped = shut()
    assert "when its run completes" in (stopped.note or "")
    assert status(cell, "wc4")[0] == "Run_Shut" and accepts(cell, "wc4") == []
    assert ear.wait("Run_Complete of run 21", lambda m: m.machine_run_id == 21).ack_code == OK
    wait_for(lambda: status(cell, "wc4")[0] == "Shutdown", T, "Shutdown after the run")
    assert results(cell, "wc4", 21)["RESULT"] == "PASS"
    story(cell, "me:wc4", "run 1 complete", "machine shut down")

    # Setup -> Setup_Shut; its run may still start (Run_Shut) and then the machine shuts down
    start_machine(cell, "wc4", homing=False)
    assert setup_run(cell, "wc4", 22).ack_code == OK
    assert "after its run" in (shut().note or "")
    assert status(cell, "wc4")[0] == "Setup_Shut"
    assert setup_run(cell, "wc4", 23).ack_code == AckCode.NOTNOW
    assert start_run(cell, "wc4", 22).ack_code == OK
    assert status(cell, "wc4")[0] == "Run_Shut"
    ear.wait("Run_Complete of run 22", lambda m: m.machine_run_id == 22)
    wait_for(lambda: status(cell, "wc4")[0] == "Shutdown", T, "Shutdown after the run")


# ----------------------------------------------------------------------------- death of a half


def test_kill_9_of_the_me_during_a_run_is_reported_and_the_pair_rejoins_with_gwc_machine_start(
    machine_cell: Any,
) -> None:
    cell, ear = machine_cell({"id": "wc5", "kind": "dummy", "run_time": 2.0})
    start_machine(cell, "wc5", homing=False)
    assert setup_run(cell, "wc5", 31).ack_code == OK
    assert start_run(cell, "wc5", 31).ack_code == OK
    killed = time.monotonic()
    cell.kill("me", "wc5")
    wait_for(lambda: status(cell, "wc5")[0] == "Shutdown", 10, "the machine to be Shutdown")
    assert time.monotonic() - killed < 5.0, f"seen after {time.monotonic() - killed:.1f}s"
    # Told by the kernel (the WC watches its ME's process), confirmed by a ping that goes unanswered.
    wait_for(lambda: cell.log_has("wc:wc5", "the ME's process"), T, "the WC to see the ME's process exit")
    pending_alarm(cell, "ME_DIED", "wc5")
    assert ear.wait("Run_Complete(Run_Fail) of run 31", lambda m: m.machine_run_id == 31).ack_code == AckCode.RUN_FAIL
    assert accepts(cell, "wc5") == []
    story(
        cell,
        "wc:wc5",
        "ME of wc5 is dead",
        r"alarm \d+ \(ME_DIED\) raised",
        "Running -> Shutdown",
        r"run 31 complete \(Run_Fail\)",
    )

    cell.kill("wc", "wc5")  # the pair is restarted; nothing else is
    cell.start("me", "wc5")
    cell.start("wc", "wc5", start=False)
    started = gwc(cell, "machine", "start", "wc5")
    assert started.returncode == 0, started.stderr + started.stdout
    assert "wc:wc5: started" in started.stdout
    assert status(cell, "wc5")[0] == "Idle"
    assert setup_run(cell, "wc5", 32).ack_code == OK
    assert start_run(cell, "wc5", 32).ack_code == OK
    assert ear.wait("Run_Complete of run 32", lambda m: m.machine_run_id == 32).ack_code == OK
    assert results(cell, "wc5", 32)["RESULT"] == "PASS"


def test_an_idle_wc_shut_down_while_it_could_not_be_heard_starts_again_on_one_machine_start(
    machine_cell: Any,
) -> None:
    # Frozen past its liveness (as a WC behind a cut cable is), wc3 still counts itself Idle and started;
    # the Machine Server has it Shutdown. `gwc machine start` must start it again, not answer "already
    # started" and leave it Shutdown.
    cell, _ = machine_cell(
        {"id": "wc3", "kind": "dummy", "run_time": 0.2},
        prepare="update me_config set liveness_s = 1 where machine_id = 'wc3'",
    )
    start_machine(cell, "wc3", homing=False)
    wc = cell.pid("wc", "wc3")
    assert wc is not None
    os.kill(wc, signal.SIGSTOP)
    try:
        wait_for(lambda: status(cell, "wc3")[0] == "Shutdown", T, "the Machine Server to shut the silent wc3 down")
    finally:
        os.kill(wc, signal.SIGCONT)
    started = gwc(cell, "machine", "start", "wc3")
    assert started.returncode == 0 and "wc:wc3: started" in started.stdout, started.stderr + started.stdout
    assert status(cell, "wc3")[0] == "Idle" and accepts(cell, "wc3") != []
    assert cell.log_has("wc:wc3", "starting it again")


@pytest.mark.parametrize(
    "liveness, after", [(30, "Idle"), (1, "Shutdown")], ids=["back-before-liveness", "shut-down-by-liveness"]
)
def test_kill_9_of_the_wc_during_a_run_the_restarted_wc_stores_the_run_its_me_finished(
    machine_cell: Any, liveness: int, after: str
) -> None:
    # The run completes with no WC: the ME's RUN_COMPL waits in the queue. With a long liveness the
    # machine is still Running when the WC is back: it resumes the run and serves again. With a short
    # one the Machine Server has shut the machine down meanwhile: the part was made all the same, so
    # its results are stored and announced and the machine stays Shutdown (the soak, seed 1991,
    # found that results file left behind).
    cell, ear = machine_cell(
        {"id": "wc6", "kind": "dummy", "run_time": 2.0},
        prepare=f"update me_config set liveness_s = {liveness} where machine_id = 'wc6'",
    )
    start_machine(cell, "wc6", homing=False)
    assert setup_run(cell, "wc6", 41).ack_code == OK
    assert start_run(cell, "wc6", 41).ack_code == OK
    cell.kill("wc", "wc6")
    if after == "Shutdown":
        wait_for(lambda: status(cell, "wc6")[0] == "Shutdown", T, "the Machine Server to shut the machine down")
    wait_for(lambda: cell.log_has("me:wc6", "run 1 complete"), T, "the ME to finish its run")
    results_file = cell.cfg.results_dir / "wc6" / "run-41.txt"
    assert results_file.exists()
    cell.start("wc", "wc6", start=False)
    assert ear.wait("Run_Complete of run 41", lambda m: m.machine_run_id == 41).ack_code == OK
    assert results(cell, "wc6", 41)["RESULT"] == "PASS"
    assert cell.query("select ack_code from machine_run_outcome where machine_id = 'wc6' and machine_run_id = 41") == [
        ("ACK_OK",)
    ]
    assert not results_file.exists(), "the results file is removed once stored"
    wait_for(lambda: status(cell, "wc6")[0] == after, T, f"{after} after the run")
    if after == "Idle":
        story(cell, "wc:wc6", "Running \\(run 41\\): resuming it", "41: 5 results stored", "resumed: Idle")
        assert setup_run(cell, "wc6", 42).ack_code == OK  # and it serves the cell again
    else:
        assert accepts(cell, "wc6") == []
        story(cell, "wc:wc6", "run 41 ended while its machine was Shutdown", "41: 5 results stored")


def test_kill_9_of_both_halves_the_restarted_wc_finds_a_fresh_me_refuses_setups_and_shuts_the_machine_down(
    machine_cell: Any,
) -> None:
    # BUG-3: WC and ME killed and restarted before the Machine Server notices (liveness 30 s here): the
    # status still says Idle, but the new ME is shut down. The WC checks its ME before serving anything.
    cell, ear = machine_cell(
        {"id": "wc5", "kind": "dummy", "run_time": 0.3},
        prepare="update me_config set liveness_s = 30 where machine_id = 'wc5'",
    )
    start_machine(cell, "wc5", homing=False)
    cell.kill("wc", "wc5")
    cell.kill("me", "wc5")
    cell.start("me", "wc5")
    cell.start("wc", "wc5", start=False)
    refused = setup_run(cell, "wc5", 51)  # at once, while the WC may still be checking its ME
    assert refused.ack_code == AckCode.NOTNOW, refused
    wait_for(lambda: status(cell, "wc5")[0] == "Shutdown", T, "the machine to be Shutdown")
    pending_alarm(cell, "ME_DIED", "wc5")
    assert accepts(cell, "wc5") == []
    assert setup_run(cell, "wc5", 52).ack_code == AckCode.NOTNOW
    assert not cell.log_has("me:wc5", "SETUP_RUN"), "no SETUP_RUN may reach a shut-down ME"
    story(
        cell,
        "wc:wc5",
        r"Idle \(run None\): resuming it",
        "ME of wc5 is dead",
        "answers that it is shut down",
        "Idle -> Shutdown",
    )

    started = gwc(cell, "machine", "start", "wc5")  # the operator's way back
    assert started.returncode == 0, started.stderr + started.stdout
    assert status(cell, "wc5")[0] == "Idle"
    assert setup_run(cell, "wc5", 53).ack_code == OK
    assert start_run(cell, "wc5", 53).ack_code == OK
    assert ear.wait("Run_Complete of run 53", lambda m: m.machine_run_id == 53).ack_code == OK


def test_a_setup_that_starts_its_run_answers_once_running_and_large_results_stay_in_the_table(
    machine_cell: Any,
) -> None:
    cell, ear = machine_cell({"id": "wc3", "kind": "dummy", "run_time": 0.5, "results": {"PROFILE": "x" * 2100}})
    start_machine(cell, "wc3", homing=False)
    refused = setup_run(cell, "wc3", 51, recipe=None, op="no_such_op", start=True)  # a setup needs a recipe
    assert refused.ack_code == AckCode.REC_INVAL and "no recipe for op type no_such_op" in (refused.note or "")
    assert status(cell, "wc3")[0] == "Idle"  # refused: nothing set up, nothing started
    set_up = setup_run(cell, "wc3", 52, recipe=None, start=True)  # the lot's one conversation for both
    assert (set_up.ack_code, set_up.recipe_id) == (OK, "dummy_recipe")
    assert status(cell, "wc3")[:3] == ("Running", "dummy_recipe", 52)  # answered once Running
    again = start_run(cell, "wc3", 52)  # a START_RUN after it finds the run started: refused, not run twice
    assert again.ack_code == AckCode.NOTNOW
    done = ear.wait("Run_Complete of run 52", lambda m: m.machine_run_id == 52)
    assert done.ack_code == OK and done.results is None  # over INLINE_RESULTS: read from the table
    assert results(cell, "wc3", 52)["PROFILE"] == "x" * 2100
    story(cell, "wc:wc3", r"SETUP_RUN run 52 recipe \(ours\) op dummy_op and start", "Idle -> Setup", "-> Running")
    story(cell, "wc:wc3", "set up run 52 with recipe dummy_recipe, started", r"run 52 complete \(ACK_OK\)")
    story(cell, "me:wc3", "set up with recipe dummy_recipe", r"run \d+ started", r"run \d+ complete: ACK_OK")


def test_kill_9_of_the_wc_after_it_read_run_compl_the_restarted_wc_completes_the_run_from_its_results_file(
    machine_cell: Any,
) -> None:
    # BUG-5: the dead WC had read RUN_COMPL from the queue and died before handling it. Its successor
    # finds run N Running in MACHINE_STATUS and the results file it chose for the run: it completes it.
    cell, ear = machine_cell(
        {"id": "wc2", "kind": "dummy", "run_time": 0.3},
        prepare="update me_config set liveness_s = 30 where machine_id = 'wc2'",
    )
    start_machine(cell, "wc2", homing=False)
    results_file = cell.cfg.results_dir / "wc2" / "run-427.txt"

    def run_and_lose_run_compl(run_id: int) -> Any:
        assert setup_run(cell, "wc2", run_id).ack_code == OK
        assert start_run(cell, "wc2", run_id).ack_code == OK
        cell.kill("wc", "wc2")
        with Channel(cell.cfg.ipc_prefix, "wc2", "wc", cell.log) as queue:  # what the dead WC had read
            deadline = time.monotonic() + T
            while (msg := queue.receive(max(deadline - time.monotonic(), 0.1))).message_id != MessageId.RUN_COMPL:
                pass
        assert status(cell, "wc2")[:3] == ("Running", "dummy_recipe", run_id)
        return msg

    msg = run_and_lose_run_compl(427)
    assert msg.file_name == str(results_file) and results_file.exists()
    cell.start("wc", "wc2", start=False)
    assert ear.wait("Run_Complete of run 427", lambda m: m.machine_run_id == 427).ack_code == OK
    assert results(cell, "wc2", 427)["RESULT"] == "PASS"
    wait_for(lambda: status(cell, "wc2")[0] == "Idle", T, "Idle again")
    assert not results_file.exists(), "the results file is removed once stored"
    wait_for(lambda: accepts(cell, "wc2") == ["dummy_op", "measure", "mill_chess"], T, "all operations again")
    story(
        cell,
        "wc:wc2",
        r"Running \(run 427\): resuming it",
        "run 427 ended while no WC handled it",
        "427: 5 results stored",
        r"run 427 complete \(ACK_OK\)",
        "Running -> Idle",
        "resumed: Idle",
    )

    # The same, but the results file is gone too: the ME is idle with no run, the run failed.
    run_and_lose_run_compl(428)
    (cell.cfg.results_dir / "wc2" / "run-428.txt").unlink()
    cell.start("wc", "wc2", start=False)
    lost = ear.wait("Run_Complete(Run_Fail) of run 428", lambda m: m.machine_run_id == 428)
    assert lost.ack_code == AckCode.RUN_FAIL and "results lost" in (lost.note or "")
    wait_for(lambda: status(cell, "wc2")[0] == "Idle", T, "Idle again")
    pending_alarm(cell, "RUN_FAIL", "wc2")
    # Idle is written before the resumed WC serves (until then it answers Notnow, as it should): wait.
    story(
        cell, "wc:wc2", "resumed: Idle", "run 428: no results file", r"run 428 complete \(Run_Fail\)", "resumed: Idle"
    )
    assert setup_run(cell, "wc2", 429).ack_code == OK  # and it serves the cell again


# ----------------------------------------------------------------------------- the numbers


def test_gwc_bench_mq_reports_the_wc_me_round_trip_beside_the_bare_floor() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "gwc", "bench", "mq", "-n", "300", "--json"], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    for path in ("bare", "channel", "wc"):
        assert report[path]["n"] == 300 and 0 < report[path]["median_us"] <= report[path]["p99_us"], report
    # The ratio is the WC's figure over the floor's (near 1: which is larger swings with the machine's noise).
    assert report["ratio_median"] == round(report["wc"]["median_us"] / report["bare"]["median_us"], 2)


def test_a_setup_whose_run_is_not_reserved_is_given_up_and_the_machine_serves_again(machine_cell: Any) -> None:
    # The lot that set the machine up gave up or died before START_RUN (here, as no lot holds run 31,
    # MSCHED reserves nothing for it): nobody will start the run, so the WC gives the setup up.
    cell, ear = machine_cell({"id": "wc3", "kind": "dummy", "run_time": 0.1})
    start_machine(cell, "wc3", homing=False)
    assert setup_run(cell, "wc3", 31).ack_code == OK
    assert status(cell, "wc3")[:3] == ("Setup", "dummy_recipe", 31)
    wait_for(lambda: status(cell, "wc3")[0] == "Idle", 30, "the setup to be given up")
    wait_for(lambda: accepts(cell, "wc3") == ["dummy_op", "measure", "mill_chess"], T, "all operations again")
    story(cell, "wc:wc3", "set up run 31", "run 31 is set up but not reserved any more", "status Setup -> Idle")
    assert start_run(cell, "wc3", 31).ack_code == AckCode.NOTNOW
    assert setup_run(cell, "wc3", 32).ack_code == OK  # and it serves the cell again


def test_a_setup_is_answered_without_mscheds_accept_types_and_the_run_end_waits_for_them(machine_cell: Any) -> None:
    # docs/machine-interface.md 4.1: MSCHED frozen (SIGSTOP) answers nothing. The WC sets up and starts
    # the run all the same; it stores the run's results, but tells Run_Complete only once MSCHED has
    # taken the setup's accepts-nothing, so no lot can give the machine back before that.
    cell, ear = machine_cell({"id": "wc3", "kind": "dummy", "run_time": 0.05})
    start_machine(cell, "wc3", homing=False)
    msched = cell.pid("msched")
    assert msched is not None
    os.kill(msched, signal.SIGSTOP)  # kept short: under peer_timeout (2.25 s), so nobody drops it
    try:
        assert setup_run(cell, "wc3", 41).ack_code == OK
        assert start_run(cell, "wc3", 41).ack_code == OK
        wait_for(lambda: results(cell, "wc3", 41), T, "the run's results stored")
        with pytest.raises(AssertionError, match="timed out"):
            ear.wait("no Run_Complete while MSCHED is frozen", lambda m: m.machine_run_id == 41, timeout=0.5)
    finally:
        os.kill(msched, signal.SIGCONT)
    assert ear.wait("Run_Complete of run 41", lambda m: m.machine_run_id == 41).ack_code == OK
    story(cell, "wc:wc3", "set up run 41", "accept types: none", r"run 41 complete \(ACK_OK\)")
    wait_for(lambda: accepts(cell, "wc3") == ["dummy_op", "measure", "mill_chess"], T, "all operations again")


def test_a_machine_sets_up_with_the_approved_copy_it_holds_and_asks_the_ers_only_for_what_it_lacks(
    machine_cell: Any,
) -> None:
    # docs/machine-interface.md 4.1: the setup's read gives the approved version and its sha256; a copy
    # held by the machine that matches is used as it is, anything else comes from the ERS.
    cell, ear = machine_cell({"id": "wc3", "kind": "dummy", "run_time": 0.05})
    start_machine(cell, "wc3", homing=False)
    held = cell.cfg.var / "recipes" / "wc3" / "dummy_recipe.v1"

    def fetched() -> int:
        return cell.log_text("ers").count("recipe dummy_recipe v1 to wc3")

    def run(run_id: int) -> None:
        assert setup_run(cell, "wc3", run_id).ack_code == OK
        assert start_run(cell, "wc3", run_id).ack_code == OK
        assert ear.wait(f"Run_Complete of run {run_id}", lambda m: m.machine_run_id == run_id).ack_code == OK
        wait_for(lambda: status(cell, "wc3")[0] == "Idle", T, "Idle again")

    run(61)  # the machine's first setup with v1: from the ERS
    assert fetched() == 1 and held.exists()
    run(62)  # held, and the approved version: the ERS is not asked
    assert fetched() == 1
    approved = held.read_text()
    held.write_text(approved + "SPEED 99\n")  # the held copy changed on disk: not the approved version
    run(63)
    assert fetched() == 2 and held.read_text() == approved
    story(cell, "me:wc3", *[f"set up with recipe dummy_recipe \\({held}\\)"] * 3)
