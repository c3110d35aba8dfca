"""The production record (docs/record.md) against a known truth: one private cell, driven through a
timeline the test writes down, then read back as the operator reads it (`gwc report oee`, `gwc
downtime`, `gwc trace`, the HTML page in headless Chromium).

One cell for every check (the suite's budget): wc1 runs lots, is stopped for 20 s with the reason
"tool change", and one of its runs fails; meanwhile wc3's WC falls silent (unscheduled downtime,
liveness) and wc2, whose calendar plans no time at all, is stopped by the operator (non-scheduled).
"""

from __future__ import annotations

import asyncio
import json
import shutil
import socket
import subprocess
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from cryptography.x509.oid import ExtendedKeyUsageOID
from textual.widgets import DataTable, OptionList

from gwc.cell import shutdown, startup
from gwc.console.app import ConsoleApp
from gwc.log import open_log
from gwc.opcua.security import hash_password
from gwc.soak.private_config import write_config
from tests.e2e.lotkit import TWO_DUMMY_RUNS, gwc, import_export_all, ok, order, start_machine, steps
from tests.harness import CellHarness, until, wait_for

RUN_TIME = 0.5
DOWN_FOR = 20.0
CHROMIUM = shutil.which("chromium")


def _json(cell: CellHarness, *args: str) -> Any:
    return json.loads(ok(gwc(cell, *args, "--json")))


def _run_pawns(cell: CellHarness, n: int) -> list[int]:
    entities = order(cell, f"pawn={n}")
    import_export_all(cell, entities, timeout=60)
    return entities


def _iso(t: float) -> str:
    return datetime.fromtimestamp(t, UTC).isoformat()


def test_record_books_oee_downtime_and_genealogy_against_a_known_truth(lot_cell: Any, tmp_path: Path) -> None:
    cell = lot_cell(
        machines=[
            {"id": "wc1", "kind": "dummy", "run_time": RUN_TIME, "fail_runs": [2]},
            {"id": "wc2", "kind": "dummy", "run_time": RUN_TIME, "calendar": "never"},
            {"id": "wc3", "kind": "dummy", "run_time": RUN_TIME, "liveness": 1.5},
        ],
        # a calendar that plans no time at all, for wc2; the dummy recipe's ideal cycle
        record={"ideal_cycle_s": {"dummy_recipe": 0.4}, "calendars": {"never": {"shifts": []}}},
    )
    endpoint = f"opc.tcp://127.0.0.1:{_free_port()}/gwc/"
    cell.cfg = write_config(
        cell.cfg.path,
        {**cell.cfg.raw, "opcua": {"endpoint": endpoint, "users": {"operator": hash_password("cell-secret")}}},
    )
    script = tmp_path / "pawn.py"
    script.write_text(TWO_DUMMY_RUNS)
    cell.start_servers()
    for m in ("wc1", "wc2", "wc3"):
        cell.start_machine_processes(m)
    start_machine(cell, "wc1")
    ok(gwc(cell, "script", "register", "pawn", str(script), "--product", "pawn"))

    since = time.time()
    first = _run_pawns(cell, 2)  # 4 runs on wc1, the ME's second fails

    # the operator stops wc1 for DOWN_FOR seconds, reason "tool change"
    t0 = time.time()
    shutdown(cell.bus, "wc:wc1", "ME_SHUT", timeout=30)  # what `gwc machine stop wc1` says, timed closely
    t1 = time.time()
    ok(gwc(cell, "downtime", "reason", "wc1", "tool change"))
    stopped = (t0 + t1) / 2

    # meanwhile: wc3 up, then its WC and ME killed (silent): liveness shuts it down
    start_machine(cell, "wc3")
    cell.kill("wc", "wc3")
    cell.kill("me", "wc3")
    # and wc2, never planned, started and stopped by the operator
    start_machine(cell, "wc2")
    ok(gwc(cell, "machine", "stop", "wc2"))
    silent = wait_for(
        lambda: [e for e in _json(cell, "downtime", "list", "--machine", "wc3") if e["cause"] == "liveness"],
        15,
        "wc3's downtime for its silent WC",
    )
    assert silent[0]["e10_state"] == "unscheduled_downtime" and silent[0]["reason"] == "WC_SILENT", silent
    (off,) = _json(cell, "downtime", "list", "--machine", "wc2")
    assert off["cause"] == "operator_stop" and off["e10_state"] == "non_scheduled", off

    # while wc1 is down: the OPC UA gateway shows wc3's open downtime and takes its reason
    cell.start("opcua", timeout=60)
    asyncio.run(_reason_through_opcua(endpoint, tmp_path, "wc3", "electrical"))
    (silent,) = _json(cell, "downtime", "list", "--machine", "wc3", "--open")
    assert silent["reason"] == "electrical" and silent["e10_state"] == "unscheduled_downtime", silent
    # and the console's Record screen gives wc2's stop its reason (DOWNTIME_RSN)
    asyncio.run(_reason_from_the_console(cell, int(off["event_id"]), "cleaning"))
    (off,) = _json(cell, "downtime", "list", "--machine", "wc2")
    assert off["reason"] == "cleaning" and off["e10_state"] == "non_scheduled", off  # outside planned time still

    time.sleep(max(0.0, stopped + DOWN_FOR - time.time()))  # the downtime the test drives: 20 s, no condition
    t2 = time.time()
    startup(cell.bus, "wc:wc1", "ME_START", timeout=30)  # `gwc machine start wc1`
    t3 = time.time()
    restarted = (t2 + t3) / 2
    second = _run_pawns(cell, 1)
    until = time.time()

    rep = _json(cell, "report", "oee", "--machine", "wc1", "--since", _iso(since), "--until", _iso(until))
    (wc1,) = rep["machines"]
    assert set(wc1) == {
        "machine_id", "planned_s", "run_s", "down_s", "availability", "performance", "quality", "oee", "parts",
        "good_parts", "downtime",
    }  # fmt: skip
    assert set(rep) == {"since", "until", "machines", "cell"}
    outcomes = cell.query(
        "select ack_code from machine_run_outcome where machine_id = 'wc1' and ended_at >= %s and ended_at < %s",
        datetime.fromtimestamp(since, UTC),
        datetime.fromtimestamp(until, UTC),
    )
    parts, good = len(outcomes), sum(1 for (c,) in outcomes if c == "ACK_OK")
    assert (parts, good) == (6, 5), outcomes
    assert abs(wc1["planned_s"] - (until - since)) < 1.0, wc1
    assert abs(wc1["down_s"] - (restarted - stopped)) < 1.0, (wc1, t1 - t0, t3 - t2, restarted - stopped)
    assert abs(wc1["run_s"] - parts * RUN_TIME) < 1.0, wc1
    assert (wc1["parts"], wc1["good_parts"]) == (parts, good)
    assert wc1["downtime"] == [{"reason": "tool change", "seconds": wc1["down_s"], "events": 1}], wc1
    assert wc1["availability"] == pytest.approx(wc1["run_s"] / wc1["planned_s"])
    assert wc1["performance"] == pytest.approx(0.4 * parts / wc1["run_s"])
    assert wc1["quality"] == pytest.approx(good / parts)
    assert wc1["oee"] == pytest.approx(wc1["availability"] * wc1["performance"] * wc1["quality"])
    # wc3's silent WC counts as down time (unscheduled); wc2's stop, outside any planned time, does not
    others = _json(cell, "report", "oee", "--machine", "wc2", "--machine", "wc3", "--since", _iso(since))
    wc2, wc3 = others["machines"]
    assert wc2["planned_s"] == 0 and wc2["down_s"] == 0 and wc2["availability"] is None, wc2
    assert wc3["down_s"] > 5 and [d["reason"] for d in wc3["downtime"]] == ["electrical"], wc3
    (tool,) = [e for e in _json(cell, "downtime", "list", "--machine", "wc1") if e["reason"] == "tool change"]
    assert tool["cause"] == "operator_stop" and tool["e10_state"] == "scheduled_downtime" and tool["ended_at"]

    # genealogy: each entity's runs exactly, in order; and the reverse query
    for entity in first + second:
        tr = _json(cell, "trace", "entity", str(entity))
        assert set(tr) == {"entity_id", "lot_id", "work_order_id", "state", "steps", "actions"}
        assert [s["machine_run_id"] for s in tr["steps"]] == [s["machine_run_id"] for s in steps(cell, entity)]
        assert all(s["machine_id"] == "wc1" and s["recipe_id"] == "dummy_recipe" for s in tr["steps"]), tr
        assert [a["action"] for a in tr["actions"]] == ["import", "export"], tr
        assert all("@hi." in a["by"] for a in tr["actions"]), tr
        states = [
            s for (s,) in cell.query("select state from entity_state_history where entity_id = %s order by id", entity)
        ]
        assert states[:3] == ["created", "waiting_import", "imported"] and states[-2:] == ["waiting_export", "exported"]
    assert "States:" in ok(gwc(cell, "trace", "entity", str(first[0])))
    where = _json(cell, "trace", "where", "--machine", "wc1", "--recipe", "dummy_recipe@1")
    assert sorted({w["entity_id"] for w in where}) == sorted(first + second)
    assert len(where) == parts

    # the page, as a person sees it
    page = tmp_path / "report.html"
    ok(gwc(cell, "report", "html", "--out", str(page), "--since", _iso(since - 5), "--until", _iso(until)))
    _check_page_in_chromium(page, tmp_path, ["wc1", "wc2", "wc3"])


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def _reason_through_opcua(endpoint: str, certs: Path, machine: str, reason: str) -> None:
    """As an MES would: read the machine's Monitoring (OEE figures, open downtime), then SetDowntimeReason
    on a signed and encrypted channel as a user."""
    cert, key = certs / "client-cert.der", certs / "client-key.pem"
    await setup_self_signed_certificate(
        key, cert, "urn:gwc:test:client", "localhost", [ExtendedKeyUsageOID.CLIENT_AUTH], {"commonName": "test"}
    )
    client = Client(endpoint, timeout=30, watchdog_intervall=5.0)
    client.application_uri = "urn:gwc:test:client"
    await client.set_security(
        SecurityPolicyBasic256Sha256, str(cert), str(key), mode=ua.MessageSecurityMode.SignAndEncrypt
    )
    client.set_user("operator")
    client.set_password("cell-secret")
    await client.connect()
    try:
        ns = await client.get_namespace_index("urn:gwc:cell")

        def node(path: str) -> Any:
            return client.get_node(ua.NodeId(path, ns))

        mon = f"machines/{machine}/Monitoring"
        deadline = time.monotonic() + 15
        while not await node(f"{mon}/DowntimeOpen").read_value():
            assert time.monotonic() < deadline, f"{mon}/DowntimeOpen never true"
            await asyncio.sleep(0.2)
        assert await node(f"{mon}/DowntimeReason").read_value() == "WC_SILENT"
        assert await node(f"{mon}/DowntimeCause").read_value() == "liveness"
        oee = await node("machines/wc1/Monitoring/OEE").read_value()
        assert isinstance(oee, float) and 0 < oee <= 1, oee
        out = await node(f"machines/{machine}").call_method(ua.QualifiedName("SetDowntimeReason", ns), reason)
        assert out[0] == "ACK_OK", out
        deadline = time.monotonic() + 10
        while await node(f"{mon}/DowntimeReason").read_value() != reason:
            assert time.monotonic() < deadline, f"{mon}/DowntimeReason never {reason!r}"
            await asyncio.sleep(0.2)
    finally:
        await client.disconnect()


async def _reason_from_the_console(cell: CellHarness, event_id: int, reason: str) -> None:
    app = ConsoleApp(cell.cfg, open_log("console", cell.cfg.log_dir, "note"))
    async with app.run_test(size=(160, 45)) as pilot:
        await pilot.press("0")  # the Record screen
        table = app._views["record"].query_one("#table-record", DataTable)
        await until(pilot.pause, lambda: str(event_id) in [str(k.value) for k in table.rows], 15, "the event listed")
        oee = app._views["record"].query_one("#table-oee", DataTable)
        assert {"wc1", "wc2", "wc3", "(cell)"} <= {str(k.value) for k in oee.rows}
        table.move_cursor(row=table.get_row_index(str(event_id)))
        await pilot.press("r")
        picker = app.screen.query_one("#reasons", OptionList)
        picker.highlighted = app.screen.reasons.index(reason)  # type: ignore[attr-defined]
        await pilot.press("enter")
        await until(pilot.pause, lambda: [a for a in app.answers if f"downtime {event_id}" in a.text], 15, "the answer")
        assert app.answers[-1].ok, app.answers[-1].text
        await pilot.press("q")


def _check_page_in_chromium(page: Path, tmp_path: Path, machines: list[str]) -> None:
    if CHROMIUM is None:
        pytest.fail("chromium is not installed: bin/setup installs it (Debian: apt-get install chromium)")
    flags = [
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--window-size=1200,900",
    ]
    shot = tmp_path / "report.png"
    for extra in ([f"--screenshot={shot}"], ["--dump-dom"]):
        profile = tmp_path / f"chromium-{len(extra[0])}"
        done = subprocess.run(
            [CHROMIUM, *flags, f"--user-data-dir={profile}", *extra, page.as_uri()],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert done.returncode == 0, done.stderr[-2000:]
        if extra == ["--dump-dom"]:
            dom = done.stdout
    png = shot.read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    width, height = int.from_bytes(png[16:20], "big"), int.from_bytes(png[20:24], "big")
    assert (width, height) == (1200, 900), (width, height)
    assert len(png) > 20_000, f"a screenshot of {len(png)} bytes is blank"
    for m in machines:
        assert f'id="timeline-{m}"' in dom, f"no timeline of {m} in the rendered page"
    assert dom.count("<rect") > 10 and 'id="pareto"' in dom and 'id="oee"' in dom
