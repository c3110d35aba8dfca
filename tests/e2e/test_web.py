"""The web HMI's HTTP API against a real cell (servers, two dummy machines, the web module as a
process): log in, see the machines, start one, and the security the issue asks for (CSRF, cookie
flags, no action on GET, the lockout, a viewer crafting requests), each refusal a clear message and
an audit row. One cell for the module (tests/e2e/webkit.py)."""

from __future__ import annotations

import contextlib
import os
import re
import ssl
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from click.testing import CliRunner

from gwc.cli import cli
from gwc.users import Action
from tests.e2e.webkit import ARTIFACTS, PASSWORD, ROLE, audit_rows, client, logged_in, start_gateway, web_cell
from tests.harness import CellHarness, wait_for

pytestmark = pytest.mark.e2e


@pytest.fixture(scope="module")
def web(xprocess: Any, pg_cluster: Any) -> Iterator[tuple[CellHarness, str]]:
    with web_cell(xprocess, pg_cluster) as made:
        yield made


def status(cell: CellHarness, machine: str) -> str:
    return str(cell.query("select status from machine_status where machine_id = %s", machine)[0][0])


def test_operator_logs_in_sees_every_machine_and_starts_one_over_https(web: tuple[CellHarness, str]) -> None:
    cell, base = web
    with pytest.raises(httpx.HTTPError):  # HTTPS only: plain HTTP gets no answer it can read
        httpx.get(base.replace("https://", "http://") + "/api/machines", timeout=5)
    cert = ssl.get_server_certificate(("127.0.0.1", int(base.rsplit(":", 1)[1])))
    assert "BEGIN CERTIFICATE" in cert
    c, csrf = logged_in(base, "otto")
    with contextlib.closing(c):
        machines = c.get("/api/machines").json()
        assert {m["machine_id"] for m in machines} == {"wc1", "wc2", "cmm_wc"}
        assert all(m["status"] == "Shutdown" for m in machines)
        r = c.post("/api/machines/wc1/start", headers={"X-CSRF-Token": csrf})
        assert r.status_code == 200 and r.json()["ok"], r.text
        wait_for(lambda: status(cell, "wc1") == "Idle", 5, "wc1 Idle")
        me = c.get("/api/session").json()
        assert (me["user"], me["role"]) == ("otto", "operator") and "machine.start" in me["may"]
        assert "audit.read" not in me["may"]
        r = c.post("/api/machines/nosuch/start", headers={"X-CSRF-Token": csrf})
        assert r.status_code == 409 and "nosuch" in r.json()["error"]
    assert ("otto", "operator", "web", "machine.start", "wc1", "ok") in [row[:6] for row in audit_rows(cell, "otto")]


def test_no_action_without_its_csrf_token_on_get_or_from_another_site(web: tuple[CellHarness, str]) -> None:
    cell, base = web
    c, csrf = logged_in(base, "otto")
    with contextlib.closing(c):
        before = len(audit_rows(cell, "otto"))
        assert c.get("/api/machines/wc2/start").status_code == 405  # no action on GET
        for headers in ({}, {"X-CSRF-Token": "forged"}, {"X-CSRF-Token": csrf, "Origin": "https://evil.example"}):
            r = c.post("/api/machines/wc2/start", headers=headers)
            assert r.status_code == 403, (headers, r.text)
            assert "CSRF" in r.json()["error"] or "another site" in r.json()["error"]
        assert status(cell, "wc2") == "Shutdown"
        rows = audit_rows(cell, "otto")[before:]
        assert [(a, t, o) for _, _, _, a, t, o, _ in rows] == [("machine.start", "wc2", "refused")] * 3
        with client(base) as anon:
            no_session = anon.post("/api/machines/wc2/start", headers={"X-CSRF-Token": csrf})
        assert no_session.status_code == 401 and "log in" in no_session.json()["error"]


def test_cookies_carry_their_flags_and_a_logged_out_session_is_over(web: tuple[CellHarness, str]) -> None:
    _, base = web
    with client(base) as c:
        assert c.post("/api/login", content=b"user=otto", headers={"Content-Type": "text/plain"}).status_code == 415
        r = c.post("/api/login", json={"user": "otto", "password": PASSWORD["otto"]})
        cookie = r.headers["set-cookie"]
        for flag in ("HttpOnly", "Secure", "SameSite=strict", "Path=/"):
            assert flag.lower() in cookie.lower(), cookie
        assert r.headers["content-security-policy"].startswith("default-src 'self'")
        assert r.headers["x-frame-options"] == "DENY"
        csrf = r.json()["csrf"]
        assert c.get("/api/session").status_code == 200
        assert c.post("/api/logout", headers={"X-CSRF-Token": csrf}).status_code == 200
        c.cookies.set("gwc_session", cookie.split(";")[0].split("=", 1)[1], domain="127.0.0.1")
        assert c.get("/api/session").status_code == 401  # the token is dead on the server, not only in the jar


def test_a_viewers_session_cannot_act_by_crafting_requests(web: tuple[CellHarness, str]) -> None:
    cell, base = web
    c, csrf = logged_in(base, "vera")
    with contextlib.closing(c):
        assert c.get("/api/machines").status_code == 200
        h = {"X-CSRF-Token": csrf}
        for path, body in (
            ("/api/machines/wc1/stop", None),
            ("/api/machines/wc2/start", None),
            ("/api/alarms/1/clear", None),
            ("/api/orders", {"customer": "NJIT", "items": "milled_pawn=1"}),
            ("/api/lots/1/import", None),
        ):
            r = c.post(path, headers=h, json=body)
            assert r.status_code == 403, (path, r.text)
            assert "vera (viewer) may not" in r.json()["error"], r.text
        assert c.get("/api/audit").status_code == 403
        assert status(cell, "wc2") == "Shutdown"
    refused = [row for row in audit_rows(cell, "vera") if row[5] == "refused"]
    assert {r[3] for r in refused} >= {"machine.stop", "machine.start", "alarm.clear", "order.enter", "lot.import"}
    assert all("may not" in r[6] for r in refused)
    a, _ = logged_in(base, "ada")
    with contextlib.closing(a):
        trail = a.get("/api/audit", params={"user": "vera"}).json()
        assert trail and {t["user_name"] for t in trail} == {"vera"}


def test_ten_wrong_passwords_lock_the_login_for_a_while(web: tuple[CellHarness, str]) -> None:
    cell, base = web
    with client(base) as c:
        for _ in range(10):
            r = c.post("/api/login", json={"user": "emma", "password": "not-her-password"})
            assert r.status_code == 401 and r.json()["error"] == "wrong user name or password"
        r = c.post("/api/login", json={"user": "emma", "password": PASSWORD["emma"]})
        assert r.status_code == 429 and "locked" in r.json()["error"], r.text
        locked_at = time.monotonic()
        # [web] lockout_s is 3 s in this cell: then the right password is taken again
        wait_for(
            lambda: c.post("/api/login", json={"user": "emma", "password": PASSWORD["emma"]}).status_code == 200,
            10,
            "the lockout to end",
            interval=0.5,
        )
        assert time.monotonic() - locked_at >= 2.0
    logins = [r for r in audit_rows(cell, "emma") if r[3] == "login"]
    assert [r[5] for r in logins].count("refused") >= 11 and logins[-1][5] == "ok"


# ---------------------------------------------------------------------------------------- in a browser

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]


def lot_state(cell: CellHarness, entity: int) -> str:
    return str(cell.query("select state from lot_status where entity_id = %s", entity)[0][0])


@pytest.mark.skipif(not os.path.exists(CHROMIUM), reason="Debian's chromium is not installed (bin/setup)")
def test_operator_in_chromium_starts_a_machine_clears_an_alarm_and_enters_an_order(
    web: tuple[CellHarness, str],
) -> None:
    """Headless Chromium (Debian's) driven by Playwright: the operator logs in, sees every machine,
    starts one and sees it Idle without a reload within 2 s, starts the CMM and clears its homing
    alarm, enters an order, imports its lot and exports it when done. Screenshots in ARTIFACTS."""
    from playwright.sync_api import expect, sync_playwright

    cell, base = web
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    shots = []

    def shot(page: Any, name: str) -> None:
        path = ARTIFACTS / f"{len(shots) + 1:02d}-{name}.png"
        page.screenshot(path=str(path), full_page=True)
        shots.append(path)

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
        try:
            context = browser.new_context(ignore_https_errors=True, viewport={"width": 1280, "height": 900})
            page = context.new_page()
            page.goto(base)
            page.fill("#login-user", "otto")
            page.fill("#login-password", PASSWORD["otto"])
            page.click("#login button[type=submit]")
            expect(page.locator("#user")).to_have_text("otto (operator)")
            expect(page.locator("#login")).to_be_hidden()
            expect(page.locator("#machine-wc1")).to_be_visible()  # Idle or not: the API test may have started it
            for m in ("wc2", "cmm_wc"):
                expect(page.locator(f"#machine-{m}")).to_have_attribute("data-status", "Shutdown")
            expect(page.locator("#live")).to_have_text("live")
            shot(page, "machines")

            page.evaluate("window.__no_reload = 1")
            clicked = time.monotonic()
            page.locator("#machine-wc2 button", has_text="Start").click()
            expect(page.locator("#machine-wc2")).to_have_attribute("data-status", "Idle", timeout=2000)
            seen = time.monotonic() - clicked
            assert page.evaluate("window.__no_reload") == 1, "the page was reloaded"
            assert status(cell, "wc2") == "Idle"
            shot(page, "wc2-idle")

            page.locator("#machine-cmm_wc button", has_text="Start").click()  # it waits to be homed
            page.click("#tabs button[data-tab=alarms]")
            row = page.locator("#alarm-table tr", has_text="HOME_CMM")
            expect(row).to_have_count(1, timeout=10000)
            shot(page, "home-alarm")
            row.locator("button", has_text="Clear").click()
            expect(row).to_have_count(0, timeout=10000)
            expect(page.locator("#machine-cmm_wc")).to_have_attribute("data-status", "Idle", timeout=10000)

            page.click("#tabs button[data-tab=orders]")
            page.select_option("#order-customer", "NJIT")
            page.select_option("#order-product", "milled_pawn")
            page.fill("#order-quantity", "1")
            page.click("#order-form button[type=submit]")
            expect(page.locator("#message")).to_contain_text("work order", timeout=30000)
            (entity,) = [e for (e,) in cell.query("select entity_id from lot_status order by entity_id")]
            page.click("#tabs button[data-tab=lots]")
            lot_row = page.locator("#lot-table tr", has=page.locator(f"td:text-is('{entity}')"))
            lot_row.locator("button", has_text="Import").click(timeout=30000)
            shot(page, "imported")
            lot_row.locator("button", has_text="Export").click(timeout=60000)
            expect(lot_row).to_contain_text("exported", timeout=10000)
            shot(page, "exported")
            page.click("#tabs button[data-tab=orders]")
            expect(page.locator("#order-table")).to_contain_text("DONE")
            shot(page, "order-done")
        finally:
            browser.close()
    assert lot_state(cell, entity) == "exported"
    assert seen <= 2.0, f"wc2 showed Idle {seen:.2f} s after the click"
    acts = [(r[3], r[4], r[5]) for r in audit_rows(cell, "otto")]
    for act in (
        ("machine.start", "wc2", "ok"),
        ("machine.start", "cmm_wc", "ok"),
        ("order.enter", "new order", "ok"),
        ("lot.import", str(entity), "ok"),
        ("lot.export", str(entity), "ok"),
    ):
        assert act in acts, act
    assert any(a == "alarm.clear" and o == "ok" for a, _, o in acts)
    cleared_by = cell.query("select cleared_by from alarms where alarm_id = 'HOME_CMM'")[0][0]
    assert cleared_by == "web:otto"
    for p in shots:
        assert p.stat().st_size > 10_000, f"{p} looks blank"
    print(f"wc2 Idle on the page {seen:.2f} s after the click; screenshots: {', '.join(p.name for p in shots)}")


# ---------------------------------------------------------------------------------------- door by door

USERS = list(PASSWORD)  # ada (admin), vera (viewer), otto (operator), emma (engineer)


def test_the_role_table_holds_door_by_door_each_refusal_said_and_audited(
    web: tuple[CellHarness, str], tmp_path: Path, monkeypatch: Any
) -> None:
    """The whole role table (docs/users.md), at every door that offers each action: the web (its HTTP
    API), `gwc`, the console, OPC UA. Every role that may passes the door (the act is done, or its
    module answers about the object, never `may not`); every other role is refused with a message
    naming who may, and an audit row `refused` (tests/e2e/doorwalk.py)."""
    from gwc.hi.door import COMMAND_ACTIONS
    from gwc.opcua.door import METHOD_ACTIONS
    from gwc.users.roles import LOWEST, Role, allowed
    from gwc.web.app import WEB_ACTIONS
    from tests.e2e import doorwalk

    # the walk covers every action each door offers, and every action of the table is offered somewhere
    assert set(doorwalk.WEB_CALLS) == set(WEB_ACTIONS.values())
    assert {tuple(args[: len(k)]) for _, args in doorwalk.GWC_CALLS for k in COMMAND_ACTIONS} >= set(COMMAND_ACTIONS)
    assert all(
        COMMAND_ACTIONS.get(args[:2], COMMAND_ACTIONS.get(args[:1])) == a
        for a, args in doorwalk.GWC_CALLS
        if args[0] not in ("user", "audit")
    )
    assert set(doorwalk.opcua_calls()) == set(METHOD_ACTIONS)
    offered = {*WEB_ACTIONS.values(), *(a for a, _ in doorwalk.GWC_CALLS), *doorwalk.CONSOLE_CALLS}
    assert offered | set(METHOD_ACTIONS.values()) == set(LOWEST)

    cell, base = web
    before = len(audit_rows(cell))
    began = time.monotonic()

    def role(user: str) -> Role:
        return Role[ROLE[user]]

    def judged(door: str, user: str, action: Any, answer: doorwalk.Answer) -> None:
        may_ = allowed(role(user), action)
        assert answer.refused != may_, (door, user, action, answer.text)
        if answer.refused and door != "opcua":  # OPC UA says it in its status code: BadUserAccessDenied
            assert f"{user} ({ROLE[user]}) may not" in answer.text, (door, user, action, answer.text)
        if may_:
            assert "may not" not in answer.text, (door, user, action, answer.text)

    timings = {}
    for (user, action), answer in doorwalk.walk_web(base, USERS).items():
        judged("web", user, action, answer)
    timings["web"] = time.monotonic() - began
    for (user, args), answer in doorwalk.walk_gwc(cell, USERS).items():
        judged("gwc", user, dict((tuple(a), x) for x, a in doorwalk.GWC_CALLS)[args], answer)
    timings["gwc"] = time.monotonic() - began - sum(timings.values())
    for (user, action), answer in doorwalk.walk_console(cell, USERS, monkeypatch).items():
        judged("console", user, action, answer)
    timings["console"] = time.monotonic() - began - sum(timings.values())
    # OPC UA: Start on wc1 and Stop on wc2 find them already so (the otto's acts here are audited too)
    c, csrf = logged_in(base, "otto")
    with contextlib.closing(c):
        for path in ("/api/machines/wc1/start", "/api/machines/wc2/stop"):
            assert c.post(path, headers={"X-CSRF-Token": csrf}).status_code == 200
    start_gateway(cell)
    gate = time.monotonic()
    for (user, method), answer in doorwalk.walk_opcua(cell, tmp_path, USERS).items():
        judged("opcua", user, METHOD_ACTIONS[method], answer)
    timings["opcua"] = time.monotonic() - gate

    # the trail: for each door, user and action walked, rows `refused` exactly when the role may not
    rows = audit_rows(cell)[before:]
    walked: dict[str, set[Action]] = {
        "web": {a for a in WEB_ACTIONS.values() if a is not Action.VIEW},  # a GET is not an act: not audited
        "gwc": {a for a, _ in doorwalk.GWC_CALLS},
        "console": set(doorwalk.CONSOLE_CALLS),
        "opcua": set(METHOD_ACTIONS.values()),
    }
    for door, actions in walked.items():
        for user in USERS:
            for action in actions:
                mine = [r for r in rows if (r[0], r[2], r[3]) == (user, door, action.value)]
                assert mine, (door, user, action)
                if allowed(role(user), action):
                    assert all(r[5] != "refused" for r in mine), (door, user, action, mine)
                else:
                    assert all(r[5] == "refused" and f"{user} ({ROLE[user]}) may not" in r[6] for r in mine), (
                        door,
                        user,
                        action,
                        mine,
                    )
    cells = sum(len(a) for a in walked.values()) * len(USERS)
    print(
        f"role table walked: {cells} door x action x user cells; "
        + ", ".join(f"{k} {v:.1f} s" for k, v in timings.items())
    )


@pytest.mark.soak
@pytest.mark.timeout(600)
@pytest.mark.skipif(not os.path.exists(CHROMIUM), reason="Debian's chromium is not installed (bin/setup)")
def test_bench_web_compares_the_cell_with_and_without_browsers_open(tmp_path: Path, database_url: str) -> None:
    """`gwc bench web`: one pair of rounds on a real cell with the web module, two browsers in the second."""
    from tests.e2e.test_bench_cell import bench

    args = ("web", "--machines", "2", "--lots", "5", "--pairs", "1", "--browsers", "2")
    result = bench(tmp_path, database_url, *args, timeout=580)
    assert [r["browsers"] for r in result["rounds"]] == [0, 2]
    without, with_browsers = result["median_without_browsers"], result["median_with_browsers"]
    assert without["lots_per_s"] > 0 and with_browsers["lots_per_s"] > 0
    assert without["browsers_cpu_ms_per_lot"] == 0 < with_browsers["browsers_cpu_ms_per_lot"]  # they were open
    assert with_browsers["web_cpu_ms_per_lot"] > 0
    assert result["check_held"] is True, result["check_breaches"]


# ------------------------------------------------------------------------- the record and quality pages


def test_record_quality_and_genealogy_are_read_through_the_api(web: tuple[CellHarness, str]) -> None:
    """What the record's pages draw, as an MES tool reads it: a viewer may read it all; a bad window or
    an unknown entity is a clear 400, no session a 401."""
    _, base = web
    with client(base) as anon:
        assert anon.get("/api/record").status_code == 401
    c, _ = logged_in(base, "vera")
    with contextlib.closing(c):
        rec = c.get("/api/record", params={"since": "1h"}).json()
        machines = {"wc1", "wc2", "cmm_wc"}
        assert {m["machine_id"] for m in rec["oee"]["machines"]} == machines
        assert set(rec["timelines"]) == machines and rec["reasons"]
        assert all(seg["e10"] for segs in rec["timelines"].values() for seg in segs)
        assert isinstance(c.get("/api/spc").json(), list)
        assert isinstance(c.get("/api/trace/where", params={"machine": "wc1"}).json(), list)
        assert {r["recipe_id"] for r in c.get("/api/recipes").json()}
        for path, params, says in (
            ("/api/record", {"since": "yesterday-ish"}, "is not a time"),
            ("/api/trace/entity/999999", {}, "unknown lot entity 999999"),
            ("/api/trace/where", {}, "say where"),
        ):
            r = c.get(path, params=params)
            assert r.status_code == 400 and says in r.json()["error"], (path, r.text)


@pytest.fixture(scope="module")
def engineer_page(web: tuple[CellHarness, str]) -> Iterator[Any]:
    """One headless Chromium for the record's pages, logged in as emma (engineer: she may give a downtime
    its reason and approve a recipe)."""
    if not os.path.exists(CHROMIUM):
        pytest.skip("Debian's chromium is not installed (bin/setup)")
    from playwright.sync_api import expect, sync_playwright

    _, base = web
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
        try:
            page = browser.new_context(ignore_https_errors=True, viewport={"width": 1280, "height": 900}).new_page()
            page.goto(base)
            page.fill("#login-user", "emma")
            page.fill("#login-password", PASSWORD["emma"])
            page.click("#login button[type=submit]")
            expect(page.locator("#user")).to_have_text("emma (engineer)")
            expect(page.locator("#live")).to_have_text("live")
            yield page
        finally:
            browser.close()


def keep(page: Any, name: str) -> Path:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    path = ARTIFACTS / f"record-{name}.png"
    page.screenshot(path=str(path), full_page=True)
    assert path.stat().st_size > 10_000, f"{path} looks blank"
    return path


def test_oee_page_shows_each_machine_and_the_cell(engineer_page: Any) -> None:
    from playwright.sync_api import expect

    page = engineer_page
    page.click("#tabs button[data-tab=oee]")
    for m in ("wc1", "wc2", "cmm_wc", "(cell)"):
        expect(page.locator("#oee-table")).to_contain_text(m)
    assert page.locator("#oee-chart rect").count() == 4 * 4  # availability, performance, quality, OEE
    keep(page, "oee")


def test_downtime_page_gives_a_stop_its_reason_live_and_audited(
    web: tuple[CellHarness, str], engineer_page: Any
) -> None:
    """wc1 stopped through the API opens a downtime event; the page shows it live, emma gives it a reason
    of the tree, the Machine Server stores it, the page shows it, the trail has it."""
    from playwright.sync_api import expect

    cell, base = web
    c, csrf = logged_in(base, "otto")
    with contextlib.closing(c):
        assert c.post("/api/machines/wc1/start", headers={"X-CSRF-Token": csrf}).status_code == 200
        wait_for(lambda: status(cell, "wc1") == "Idle", 10, "wc1 Idle")
        assert c.post("/api/machines/wc1/stop", headers={"X-CSRF-Token": csrf}).status_code == 200
    wait_for(lambda: cell.query("select 1 from downtime_events where machine_id = 'wc1' and ended_at is null"), 10, "")
    (event,) = cell.query("select max(event_id) from downtime_events where machine_id = 'wc1' and ended_at is null")[0]
    reason = next(iter(cell.cfg.record.reasons))
    page = engineer_page
    page.click("#tabs button[data-tab=downtime]")
    row = page.locator("#downtime-table tr", has=page.locator(f"td:text-is('{event}')"))
    expect(row).to_have_count(1, timeout=15000)  # the record topic: read at most every 5 s
    row.locator("select").select_option(reason)
    row.locator("button", has_text="Set reason").click()
    expect(page.locator("#message")).to_contain_text(f"downtime {event}: {reason}")
    expect(row.locator("td").nth(5)).to_have_text(reason, timeout=10000)  # read again at once, sent live
    keep(page, "downtime")
    assert cell.query("select reason, reason_by from downtime_events where event_id = %s", event)[0] == (
        reason,
        "web:emma",
    )
    assert ("emma", "engineer", "web", "downtime.reason", str(event), "ok") in [r[:6] for r in audit_rows(cell)]


def test_timeline_page_draws_each_machines_e10_states(engineer_page: Any) -> None:
    from playwright.sync_api import expect

    page = engineer_page
    page.click("#tabs button[data-tab=timeline]")
    for m in ("wc1", "wc2", "cmm_wc"):
        expect(page.locator(f"#timeline-{m}")).to_be_attached()
    # wc1 was started and stopped (the downtime test): productive or standby, then down, drawn live
    line = page.locator("#timeline-wc1 rect")
    expect(line.last).to_have_attribute("data-e10", re.compile("downtime|non_scheduled"), timeout=15000)
    assert {line.nth(i).get_attribute("data-e10") for i in range(line.count())} & {"standby", "productive"}
    keep(page, "timeline")


def test_spc_page_charts_a_measured_feature_and_marks_a_broken_rule(
    web: tuple[CellHarness, str], engineer_page: Any
) -> None:
    """25 measurements of one feature, as a measuring run's results leave them in run_features (written
    here, as the WC's trigger would), the last far out: the chart shows it red (WE1)."""
    from playwright.sync_api import expect

    cell, _ = web
    values = [10.0 + 0.01 * ((i * 7) % 5 - 2) for i in range(24)] + [10.2]
    with cell.db() as conn:
        for i, v in enumerate(values):
            conn.execute(
                "insert into run_features (machine_run_id, machine_id, recipe_id, feature, measured, nominal, tol, at) "
                "values (%s, 'cmm_wc', 'web_spc', 'DIAM', %s, 10.0, 0.1, now() - make_interval(secs => %s))",
                (900_000 + i, v, 100 - i),
            )
    page = engineer_page
    page.reload()  # the charts are read at a page's start, then live (every 60 s at least)
    page.click("#tabs button[data-tab=spc]")
    chart = page.locator("#spc-cmm_wc-web_spc-DIAM")
    expect(chart).to_contain_text("1 rule(s) broken")
    assert chart.locator("circle").count() == 25
    assert chart.locator("circle[data-broken='1']").count() == 1
    keep(page, "spc")


def test_genealogy_page_traces_an_entity_and_searches_where(web: tuple[CellHarness, str], engineer_page: Any) -> None:
    from playwright.sync_api import expect

    cell, base = web
    (entity,) = cell.query("select max(entity_id) from lot_status")[0]
    if entity is None:  # run alone: an order of one part (its lot waits to be imported)
        c, csrf = logged_in(base, "otto")
        with contextlib.closing(c):
            r = c.post(
                "/api/orders", headers={"X-CSRF-Token": csrf}, json={"customer": "NJIT", "items": "milled_pawn=1"}
            )
            entity = r.json()["lots"][0]["entities"][0]
    page = engineer_page
    page.click("#tabs button[data-tab=genealogy]")
    page.fill("#trace-entity", str(entity))
    page.click("#trace-form button[type=submit]")
    expect(page.locator("#trace-head")).to_contain_text(f"entity {entity}, lot ")
    expect(page.locator("#trace-states")).to_contain_text("created")
    page.fill("#where-machine", "wc1")
    page.click("#where-form button[type=submit]")
    expect(page.locator("#where-table tr").first).to_contain_text("entity_id")
    keep(page, "genealogy")


def test_recipe_page_approves_a_new_version(web: tuple[CellHarness, str], engineer_page: Any, tmp_path: Path) -> None:
    from playwright.sync_api import expect

    cell, _ = web
    recipe = tmp_path / "web_recipe.txt"
    recipe.write_text("G00 X0 Y0\n")
    done = CliRunner().invoke(cli, ["recipe", "add", "web_recipe", str(recipe)], env={**cell.env(), "SUDO_USER": None})
    assert done.exit_code == 0, done.output
    page = engineer_page
    page.click("#tabs button[data-tab=recipes]")
    row = page.locator("#recipe-table tr", has=page.locator("td:text-is('web_recipe')"))
    row.locator("button", has_text="Approve v1").click()
    expect(page.locator("#message")).to_contain_text("web_recipe v1 approved")
    expect(row.locator("button")).to_have_count(0)  # the list read again: nothing left to approve
    keep(page, "recipes")
    assert cell.query("select approved from recipe_versions where recipe_id = 'web_recipe'") == [(True,)]
    assert ("emma", "engineer", "web", "recipe.approve", "web_recipe", "ok") in [r[:6] for r in audit_rows(cell)]
