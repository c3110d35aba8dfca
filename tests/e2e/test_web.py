"""The web HMI's HTTP API against a real cell (servers, two dummy machines, the web module as a
process): log in, see the machines, start one, and the security the issue asks for (CSRF, cookie
flags, no action on GET, the lockout, a viewer crafting requests), each refusal a clear message and
an audit row. One cell for the module (tests/e2e/webkit.py)."""

from __future__ import annotations

import contextlib
import ssl
import time
from collections.abc import Iterator
from typing import Any

import httpx
import pytest

from tests.e2e.webkit import PASSWORD, audit_rows, client, logged_in, web_cell
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
        assert {m["machine_id"] for m in machines} == {"wc1", "wc2"}
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
