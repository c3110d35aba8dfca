"""Quality's arithmetic and formats (docs/quality.md): recipe lines, run sheets, the mill's process,
SPC's rules and capability, the EWMA controller, and the trigger that stores a run's features."""

from __future__ import annotations

import asyncio
import itertools
import logging
import random
from pathlib import Path
from typing import Any

import pytest

from gwc.errors import ConfigError
from gwc.ipc.codes import AckCode
from gwc.ipc.mq import MessageId
from gwc.lot.model import Operation, Run
from gwc.me.results import read_results
from gwc.quality import spc
from gwc.quality.feedback import feed_forward, next_offset
from gwc.quality.lot import Quality, ToolWorn
from gwc.quality.process import MillProcess, Tool, read_part, write_part
from gwc.quality.recipe import Feature, FeedbackSettings, features_of, feedback_of
from gwc.quality.sheet import RunSheet, from_message, read_sheet, sheet_of, with_sheet, write_sheet
from tests.unit.test_me import Running, machine, recipe  # noqa: F401 (machine: the fixture of real MEs)

RECIPE = (
    "# mill_pawn\nFEATURE DIAMETER 25.00 0.05\nFEATURE HEIGHT 40 0.1\nFEATURE bad x 1\n"
    "FEEDBACK EWMA 0.3 STEP 0.02 LIMIT 0.12\n"
)


def test_recipe_lines_give_features_and_feedback() -> None:
    assert features_of(RECIPE) == [Feature("DIAMETER", 25.0, 0.05), Feature("HEIGHT", 40.0, 0.1)]
    assert feedback_of(RECIPE) == FeedbackSettings(0.3, 0.02, 0.12)
    assert feedback_of("FEEDBACK EWMA 1.5 STEP 0.02 LIMIT 0.12\n") is None  # a weight past 1 is no EWMA
    assert Feature("D", 25.0, 0.05).passes(25.05) and not Feature("D", 25.0, 0.05).passes(24.94)


def test_run_sheet_goes_after_the_recipe_and_comes_back(tmp_path: Path) -> None:
    recipe = tmp_path / "mill_pawn.v2"
    recipe.write_text(RECIPE.rstrip("\n"))
    sheet = from_message({"workpiece": 7, "tool": 2, "offsets": {"DIAMETER": -0.0123}}, 9)
    path = write_sheet(recipe, sheet)
    assert path != recipe and recipe.read_text() == RECIPE.rstrip("\n"), "the approved recipe is not changed"
    assert path.read_text().startswith(RECIPE)
    assert sheet_of(path) == RunSheet(9, 7, 2, {"DIAMETER": -0.0123})
    assert sheet_of(recipe) is None and read_sheet("no sheet") is None
    assert sheet.results() == {"OFFSET.DIAMETER": "-0.012300", "WORKPIECE": "7"}


@pytest.mark.parametrize(
    "bad",
    [
        [],
        {"offsets": {"DIAMETER": "x"}},
        {"offsets": {"D IAM": 0.1}},
        {"offsets": {"D": float("nan")}},
        {"offsets": {"D": 1e9}},
        {"workpiece": -1},
        {"tool": True},
        {"other": 1},
    ],
)
def test_a_bad_run_sheet_is_refused_with_a_reason(bad: Any, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="sheet"):
        from_message(bad, 1)
    recipe = tmp_path / "r"
    recipe.write_text("x\n")

    async def fetch() -> tuple[Path | None, str]:
        return recipe, ""

    path, why = asyncio.run(with_sheet(fetch(), bad, 1))
    assert path is None and "sheet" in why


def test_the_mill_cuts_with_bias_wear_shift_and_seeded_noise(tmp_path: Path) -> None:
    p = MillProcess.from_options(
        "m", {"seed": 1, "bias": {"D": 0.01}, "wear": {"D": 0.001}, "shift": {"after": 5, "D": 0.1}}
    )
    assert p is not None and MillProcess.from_options("m", None) is None
    feats = [Feature("D", 25.0, 0.05)]
    assert p.cut(feats, None, 0, 1, None) == {"D": 25.01}
    assert p.cut(feats, None, 4, 1, None) == {"D": 25.014}
    assert p.cut(feats, None, 5, 1, None) == {"D": 25.115}
    assert p.cut(feats, RunSheet(1, None, 0, {"D": -0.01}), 0, 1, None) == {"D": 25.0}
    assert p.cut(feats, None, 0, 1, {"D": 24.9}) == {"D": 24.9}, "a re-milling only takes material off"
    noisy = MillProcess.from_options("m", {"seed": 3, "sigma": {"D": 0.01}})
    assert noisy is not None and noisy.cut(feats, None, 0, 4, None) == noisy.cut(feats, None, 0, 4, None)
    for bad in ({"sigma": {"D": -1}}, {"seed": "x"}, {"wear": 3}, {"oops": 1}, {"shift": {"after": -1}}):
        with pytest.raises(ConfigError):
            MillProcess.from_options("m", bad)
    write_part(tmp_path, 12, {"D": 25.01})
    assert read_part(tmp_path, 12) == {"D": 25.01} and read_part(tmp_path, 13) is None


def test_the_tool_counts_parts_and_a_tool_change_resets_them(tmp_path: Path) -> None:
    tool = Tool(tmp_path)
    assert [tool.cut_one() for _ in range(3)] == [0, 1, 2]
    assert Tool(tmp_path).parts == 3, "kept across ME restarts"
    assert not tool.seen(0) and tool.seen(1) and tool.parts == 0 and not tool.seen(1)


def series(n: int, shift_at: int, shift: float, seed: int = 5) -> list[float]:
    rng = random.Random(seed)
    return [25.0 + rng.gauss(0, 0.005) + (shift if i >= shift_at else 0.0) for i in range(n)]


def test_western_electric_rules() -> None:
    lim = spc.Limits(0.0, 1.0, 1.128)
    assert spc.broken_at([0, 0, 3.5], lim, 2, spc.DEFAULT_RULES) == ["WE1"]
    assert "WE2" in spc.broken_at([2.5, 0, 2.5], lim, 2, spc.DEFAULT_RULES)
    assert "WE2" not in spc.broken_at([2.5, 0, -2.5], lim, 2, spc.DEFAULT_RULES)
    assert "WE3" in spc.broken_at([1.5, 1.5, 0, 1.5, 1.5], lim, 4, spc.DEFAULT_RULES)
    assert "WE4" in spc.broken_at([0.1] * 8, lim, 7, spc.DEFAULT_RULES)
    assert spc.broken_at([0.1] * 8, lim, 7, ("WE1",)) == [], "only the rules configured"
    assert "N3" in spc.broken_at([0, 0.1, 0.2, 0.3, 0.4, 0.5], lim, 5, ("N3",))


def test_a_two_sigma_step_shift_is_found_within_10_points_and_a_stable_process_is_quiet() -> None:
    for seed in range(20):
        values = series(60, 30, 0.010, seed)
        c = spc.chart("D", values, 24.95, 25.05, baseline=20)
        after = [v.index for v in c.violations if v.index >= 30]
        assert after and after[0] < 40, (seed, c.violations)
    quiet = spc.chart("D", series(60, 99, 0.0, 1), 24.95, 25.05, baseline=20)
    assert len(quiet.violations) <= 2
    assert quiet.cpk is not None and quiet.cpk > 2.5  # 0.05 / (3 * 0.005)


def test_capability() -> None:
    cp, cpk = spc.capability([24.99, 25.0, 25.01, 25.0], 24.95, 25.05)
    assert cp is not None and cpk is not None and cp == pytest.approx(cpk) and cp > 1.33
    _, off = spc.capability([25.03, 25.04, 25.05, 25.04], 24.95, 25.05)
    assert off is not None and off < 1
    assert spc.capability([1.0], 0, 2) == (None, None)
    assert spc.drawing(spc.chart("D", series(30, 99, 0.0), 24.95, 25.05))


def test_ewma_follows_a_wearing_tool_within_its_limits() -> None:
    fb = FeedbackSettings(0.3, 0.02, 0.12)
    history: list[tuple[float, float]] = []
    offsets = []
    for n in range(400):
        adv = next_offset(history, fb)
        offsets.append(adv.offset)
        d = 0.01 + 0.0005 * n  # bias and wear
        history.append((adv.offset, adv.offset + d))  # measured - nominal, noiseless
        if adv.worn:
            break
    assert all(abs(b - a) <= 0.02 + 1e-9 for a, b in itertools.pairwise(offsets))
    assert abs(history[60][1]) < 0.005, "the error stays small while the tool wears"
    assert adv.worn and abs(adv.offset) <= 0.12 + 1e-9, "past the limit: the tool is worn out"
    assert next_offset([], fb).offset == 0.0, "after a tool change: from zero"
    assert feed_forward(-0.01, 0.03) == -0.04


def _store_run(conn: Any, run: int, machine: str, results: dict[str, str]) -> None:
    """What the WC's results statement does: the results and the outcome, one statement (as gwc_wc)."""
    conn.execute("SET ROLE gwc_wc")
    conn.execute(
        "WITH results AS (INSERT INTO machine_run_result (machine_run_id, machine_id, param, value) "
        "SELECT %s, %s, p, v FROM unnest(%s::text[], %s::text[]) AS r (p, v)) "
        "INSERT INTO machine_run_outcome (machine_run_id, machine_id, ack_code, note) VALUES (%s, %s, 'ACK_OK', '')",
        (run, machine, list(results), list(results.values()), run, machine),
    )
    conn.execute("RESET ROLE")
    conn.commit()


def test_a_runs_features_are_stored_as_numbers_with_it_by_the_wcs_own_statement(db_conn: Any) -> None:
    content = b"# v2\nFEATURE DIAMETER 25.00 0.05\nFEATURE HEIGHT 40.00 0.10\n"
    db_conn.execute("UPDATE recipe_versions SET approved = false WHERE recipe_id = 'mill_pawn'")
    db_conn.execute(
        "INSERT INTO recipe_versions (recipe_id, version, content, checksum, approved) "
        "VALUES ('mill_pawn', 2, %s, encode(sha256(%s), 'hex'), true)",
        (content, content),
    )
    db_conn.commit()
    _store_run(db_conn, 1, "mazak", {"RECIPE": "mill_pawn", "OFFSET.DIAMETER": "-0.010000", "OFFSET.HEIGHT": "0"})
    _store_run(db_conn, 2, "wc1", {"RECIPE": "mill_pawn", "WORKPIECE": "1", "DIAMETER": "25.061", "HEIGHT": "oops"})
    _store_run(db_conn, 3, "wc2", {"RECIPE": "dummy_recipe", "DIAMETER": "25.0"})  # a recipe without features
    rows = db_conn.execute(
        "SELECT machine_run_id, feature, measured, offset_used, workpiece, in_tol FROM run_features "
        "ORDER BY machine_run_id, feature"
    ).fetchall()
    assert rows == [
        (1, "DIAMETER", None, -0.01, None, None),
        (1, "HEIGHT", None, 0.0, None, None),
        (2, "DIAMETER", 25.061, None, 1, False),  # HEIGHT "oops" is no number: left out, the results kept
    ]
    assert db_conn.execute("SELECT count(*) FROM machine_run_result WHERE machine_run_id = 2").fetchone()[0] == 4


# ----------------------------------------------------------------------------- the machines (real MEs, threads)

SHEET = "# run sheet (gwc): this run's own lines; the recipe above is the approved version\n"


def run_once(m: Running, tmp_path: Path, text: str) -> dict[str, str]:
    """ME_START, SETUP_RUN with this recipe copy, START_RUN, wait for RUN_COMPL: the results file."""
    if m.me is not None and m.me.state.value == "shutdown":
        assert m.ask(MessageId.ME_START).ack_code == AckCode.ACK_OK
    assert m.ask(MessageId.SETUP_RUN, file_name=recipe(tmp_path, text), recipe_id="r").ack_code == AckCode.ACK_OK
    out = tmp_path / "results" / f"run-{m.seq}.txt"
    assert m.ask(MessageId.START_RUN, file_name=str(out), recipe_id="r").ack_code == AckCode.ACK_OK
    while True:
        msg = m.wc.receive(15)
        if msg.message_id == MessageId.RUN_COMPL:
            assert msg.ack_code == AckCode.ACK_OK, msg
            return read_results(out)


def test_a_mill_with_a_process_cuts_the_part_and_reports_its_offsets(machine: Any, tmp_path: Path) -> None:
    m = machine(
        kind="dummy", run_time=0.01, process={"seed": 1, "bias": {"DIAMETER": 0.02}, "wear": {"DIAMETER": 0.01}}
    )
    text = "FEATURE DIAMETER 25.00 0.05\n" + SHEET + "RUN 5\nTOOL 0\nOFFSET DIAMETER -0.010000\n"
    first = run_once(m, tmp_path, text)
    assert first["OFFSET.DIAMETER"] == "-0.010000" and first["TOOL_PARTS"] == "1" and "DIAMETER" not in first
    assert read_part(m.cfg.var, 5) == {"DIAMETER": 25.01}  # 25 - 0.01 + 0.02, no wear on the first part
    run_once(m, tmp_path, text.replace("RUN 5", "RUN 6"))
    assert read_part(m.cfg.var, 6) == {"DIAMETER": 25.02}  # one part's wear
    assert run_once(m, tmp_path, text.replace("RUN 5", "RUN 7").replace("TOOL 0", "TOOL 1"))["TOOL_PARTS"] == "1"
    assert read_part(m.cfg.var, 7) == {"DIAMETER": 25.01}, "a tool change: wear from zero"


def test_the_cmm_sends_each_measured_feature_over_the_serial_line(machine: Any, tmp_path: Path) -> None:
    m = machine(
        kind="cmm",
        homing_alarm=False,
        serial={"port": "sim", "baudrate": 9600, "timeout": 5.0},
        sim={"measure_time": 0.05, "gauge_sigma": 0.0},
    )
    write_part(m.cfg.var, 5, {"DIAMETER": 25.07, "HEIGHT": 40.01})
    text = "FEATURE DIAMETER 25.00 0.05\nFEATURE HEIGHT 40.00 0.10\n" + SHEET + "RUN 9\nWORKPIECE 5\nTOOL 0\n"
    results = run_once(m, tmp_path, text)
    assert (results["DIAMETER"], results["HEIGHT"]) == ("25.070000", "40.010000")
    assert results["RESULT"] == "FAIL" and results["WORKPIECE"] == "5", "the verdict from the tolerances"
    assert run_once(m, tmp_path, "FEATURE DIAMETER 25.00 0.05\n")["DIAMETER"] == "25.000000"  # a nominal part


def test_a_dummy_without_a_process_measures_the_part_it_is_given(machine: Any, tmp_path: Path) -> None:
    m = machine(kind="dummy", run_time=0.01, gauge_sigma=0.0)
    write_part(m.cfg.var, 3, {"DIAMETER": 25.01})
    results = run_once(m, tmp_path, "FEATURE DIAMETER 25.00 0.05\n" + SHEET + "RUN 4\nWORKPIECE 3\n")
    assert results["DIAMETER"] == "25.010000" and results["RESULT"] == "PASS" and results["WORKPIECE"] == "3"
    assert "DIAMETER" not in run_once(m, tmp_path, "# dummy_recipe\nRUN\n"), "today's dummy where nothing is given"


def test_the_last_tool_change_or_maintenance_starts_the_history_again(db_conn: Any) -> None:
    def read(sql: str, params: Any = ()) -> list[tuple[Any, ...]]:
        rows = db_conn.execute(sql, tuple(params)).fetchall()
        db_conn.commit()
        return list(rows)

    from gwc.quality import store

    test_a_runs_features_are_stored_as_numbers_with_it_by_the_wcs_own_statement(db_conn)
    assert store.tool_changes(read, "mazak") == 0
    # run 1 milled on the mazak with offset -0.01, its part measured by run 2: 25.061, 0.061 off
    assert store.history(read, "mazak", "mill_pawn", "DIAMETER") == [(-0.01, pytest.approx(0.061))]
    db_conn.execute(
        "INSERT INTO machine_state_history (machine_id, status, cause) VALUES ('mazak', 'Idle', 'maintenance')"
    )
    db_conn.commit()
    first = store.tool_changes(read, "mazak")
    assert first > 0 and store.history(read, "mazak", "mill_pawn", "DIAMETER") == [], "from zero after it"
    db_conn.execute("INSERT INTO tool_changes (machine_id, confirmed_by) VALUES ('mazak', 'op')")
    db_conn.commit()
    assert store.tool_changes(read, "mazak") >= first


class FakeEntity:
    """What Quality needs of an OperationEntity, on the test's database: reads, and alarms recorded."""

    def __init__(self, db_conn: Any, tmp_path: Path) -> None:
        from tests.conftest import make_config

        self.entity_id = 1
        self.cfg = make_config(tmp_path, None)
        self.log = logging.getLogger("test.quality")
        self.conn = db_conn
        self.alarms: list[tuple[str, str, str]] = []

    def read(self, sql: str, params: Any = ()) -> list[tuple[Any, ...]]:
        rows = self.conn.execute(sql, tuple(params)).fetchall()
        self.conn.commit()
        return list(rows)

    def raise_alarm(self, alarm_id: str, machine_id: str, text: str) -> int | None:
        self.alarms.append((alarm_id, machine_id, text))
        return len(self.alarms)


def _op(op_type: str, run: int, machine: str, recipe: str) -> Operation:
    return Operation(op_type, run, [Run(machine, recipe, run, "ACK_OK", {})])


def _approve(db_conn: Any, recipe_id: str, content: bytes) -> None:
    db_conn.execute("UPDATE recipe_versions SET approved = false WHERE recipe_id = %s", (recipe_id,))
    db_conn.execute(
        "INSERT INTO recipe_versions (recipe_id, version, content, checksum, approved) "
        "SELECT %s, max(version) + 1, %s, encode(sha256(%s), 'hex'), true FROM recipe_versions WHERE recipe_id = %s",
        (recipe_id, content, content, recipe_id),
    )
    db_conn.commit()


def test_the_lot_scripts_quality_feedback_feed_forward_tool_change_and_preference(db_conn: Any, tmp_path: Path) -> None:
    _approve(db_conn, "mill_pawn", b"FEATURE DIAMETER 25.00 0.05\nFEEDBACK EWMA 0.5 STEP 0.02 LIMIT 0.03\n")
    _approve(db_conn, "alum_chess_set", b"FEATURE DIAMETER 25.00 0.05\n")
    _store_run(db_conn, 1, "mazak", {"RECIPE": "mill_pawn", "OFFSET.DIAMETER": "-0.010000"})
    _store_run(db_conn, 2, "cmm_wc", {"RECIPE": "alum_chess_set", "WORKPIECE": "1", "DIAMETER": "25.061"})
    entity = FakeEntity(db_conn, tmp_path)
    q = Quality(entity)
    mill, measured = _op("mill_chess", 1, "mazak", "mill_pawn"), _op("alum_chess", 2, "cmm_wc", "alum_chess_set")

    assert q.verdict(measured) == (False, "FAIL: DIAMETER 25.0610 (25 +/- 0.05)")
    assert q.measure_sheet(mill) is not None and q.measure_sheet(measured) is not None
    # Feed forward: the part sent back is given its own correction, -0.01 - 0.061.
    again = q.mill_sheet(remill=mill, measured=measured)("mazak", "mill_pawn")
    assert again is not None and again["workpiece"] == 1 and again["offsets"]["DIAMETER"] == pytest.approx(-0.071)
    # Feedback: the estimate asks for -0.0355 (0.5 * 0.071), past LIMIT 0.03: TOOL_CHANGE, the operation asked again.
    db_conn.execute("UPDATE machine_status SET status = 'Shutdown' WHERE machine_id = 'mazak'")
    db_conn.commit()
    with pytest.raises(ToolWorn, match="mazak tool worn out"):
        q.mill_sheet()("mazak", "mill_pawn")
    assert [a[:2] for a in entity.alarms] == [("TOOL_CHANGE", "mazak")]
    # Another mill with no history yet: tried first (an untried machine counts as perfect).
    db_conn.execute("UPDATE machine_status SET status = 'Idle' WHERE machine_id IN ('mazak', 'wc2')")
    db_conn.commit()
    assert q.preferred("mill_chess") == [["wc2"], ["mazak"]]
    assert q.preferred("dummy_op") is None, "no history for the operation: the entity's own choice"
