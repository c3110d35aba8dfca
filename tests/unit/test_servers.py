"""The servers' rules that need no process: status transitions, lot actions, the recipe library's
names, the status line's words. (Their conversations are tested end to end in tests/e2e.)"""

from __future__ import annotations

import hashlib

import pytest

from gwc.config import Config
from gwc.ipc.catalogue import LOT_CLASSES, message
from gwc.ipc.codes import LotState, MachineStatus
from gwc.servers import lot, machine, recipe, status_line
from gwc.servers.alarm import AlarmServer
from gwc.servers.lot import LotServer
from gwc.servers.machine import MachineServer
from gwc.servers.recipe import RecipeServer
from gwc.servers.status_line import StatusLineServer
from gwc.servers.status_line_store import Alarm, Waiting


def test_every_status_has_its_transitions_and_shutdown_is_always_reachable() -> None:
    assert set(machine.TRANSITIONS) == set(MachineStatus)
    for frm, to in machine.TRANSITIONS.items():
        assert MachineStatus.SHUTDOWN in to and frm in to, frm
    # the WC's path through a run (6.3.2), and the ones it must never take
    for a, b in [
        (MachineStatus.SHUTDOWN, MachineStatus.IDLE),
        (MachineStatus.IDLE, MachineStatus.SETUP),
        (MachineStatus.SETUP, MachineStatus.RUNNING),
        (MachineStatus.RUNNING, MachineStatus.IDLE),
        (MachineStatus.SETUP, MachineStatus.SETUP_SHUT),
        (MachineStatus.SETUP_SHUT, MachineStatus.RUN_SHUT),
        (MachineStatus.RUNNING, MachineStatus.RUN_SHUT),
    ]:
        assert b in machine.TRANSITIONS[a], (a, b)
    for a, b in [
        (MachineStatus.SHUTDOWN, MachineStatus.RUNNING),
        (MachineStatus.SHUTDOWN, MachineStatus.SETUP),
        (MachineStatus.IDLE, MachineStatus.RUNNING),
        (MachineStatus.RUN_SHUT, MachineStatus.IDLE),
    ]:
        assert b not in machine.TRANSITIONS[a], (a, b)


def test_lot_actions_name_real_states_and_finished_entities_cannot_move_on() -> None:
    for action, (target, allowed) in lot.ACTIONS.items():
        assert target is None or target in LotState, action
        assert allowed <= set(LotState), action
    assert LotState.EXPORTED not in lot.ACTIONS["failed"][1]
    assert LotState.EXPORTED in lot.ACTIONS["import"][1]  # comes back as a new lot
    assert not lot.ACTIONS["running"][1] & {LotState.CREATED, LotState.WAITING_IMPORT, LotState.EXPORTED}


@pytest.mark.parametrize(
    "rid, ok",
    [
        ("dummy_recipe", True),
        ("alum_chess_set", True),
        ("a.b-c_1", True),
        ("../x", False),
        (".hidden", False),
        ("a/b", False),
        ("", False),
        ("x" * 65, False),
    ],
)
def test_recipe_ids_are_safe_file_names(rid: str, ok: bool) -> None:
    assert bool(recipe.RECIPE_ID.match(rid)) is ok


def test_each_version_has_its_own_library_file_and_checksum(cell_config: Config) -> None:
    p1 = recipe.version_path(cell_config, "mill_pawn", 1)
    assert p1 == cell_config.var / "recipe_library" / "mill_pawn" / "v1"
    assert recipe.version_path(cell_config, "mill_pawn", 2) != p1
    assert recipe.sha256(b"RUN\n") == hashlib.sha256(b"RUN\n").hexdigest()  # what the WC computes


def test_status_line_says_what_waits_for_the_operator() -> None:
    last = "12:00:00 wc1 Idle -> Shutdown"
    quiet = status_line.line(Waiting([], [], 0, None), last)
    assert quiet == "LAST 12:00:00 wc1 Idle -> Shutdown"
    busy = status_line.line(Waiting(list(range(1, 8)), [9], 2, Alarm(4, "odd", False)), last)
    assert busy.startswith(
        "IMPORT 7 waiting (1, 2, 3, 4, 5, ...) | EXPORT 1 waiting (9) | "
        "ALARMS 2 pending, newest #4 (unknown): odd | LAST"
    )


def test_status_line_describes_what_it_hears() -> None:
    d = status_line._describe
    assert (
        d("UPD_ME_ST", message("Update_ME_Status", machine_id="wc1", status="Shutdown", previous="Idle", note="silent"))
        == "wc1 Idle -> Shutdown (silent)"
    )
    assert (
        d("ALARM_CLE", message("Alarm_Clear", alarm_no=3, alarm_id="HOME_CMM", cleared_by="op"))
        == "alarm 3 HOME_CMM cleared by op"
    )
    assert d("LOT_MOVED", message("Lot_Moved", entity_id=4, action="export", lot_id=2)) == "entity 4 (lot 2) exported"
    assert (
        d("RUN_COMPL", message("Run_Complete", machine_id="wc1", machine_run_id=7, ack_code="Run_Fail"))
        == "wc1 run 7 failed (Run_Fail)"
    )
    assert d("CELL_EVENT", message("Cell_Event", text="hello")) == "hello"


def test_the_servers_that_ignore_lot_scripts_only_answer_a_class_a_lot_may_open() -> None:
    """A lot opens only LOT_CLASSES (its key allows no other): a server that serves none of them never
    hears from a lot, and one that only answers a lot (the ERS a proposal) starts nothing a lot hears, so
    neither need track lots (docs/protocol.md, *Peers a module ignores*)."""
    for server in (AlarmServer, RecipeServer, StatusLineServer):
        assert "lot:7".startswith(server.ignored_peers) and server.ignored_peers, server
        # The ERS answers a lot's recipe proposal as a WC answers it: addressed, and it starts nothing a lot hears.
        # The CAS answers a lot's quality alarm (SPC_RULE, TOOL_CHANGE: docs/quality.md) the same way.
        answered = {"RECIPE_PUT"} if server is RecipeServer else {"ALARM_SEND"} if server is AlarmServer else set()
        assert set(server.handlers(server.__new__(server))) & LOT_CLASSES == answered, server
    for server in (LotServer, MachineServer):  # a lot asks the first; the second broadcasts to lots
        assert not server.ignored_peers, server
