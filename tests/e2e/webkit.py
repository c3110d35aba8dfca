"""What the web tests share: one private cell (servers, two dummy machines, the web module) per test
module, with users of every role, and an HTTPS client that logs in as one of them."""

from __future__ import annotations

import contextlib
import socket
import subprocess
import sys
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
from psycopg import sql

from gwc import db
from gwc.users import Role, store
from gwc.users.passwords import hash_password
from tests.e2e.lotkit import default_machines
from tests.harness import SERVERS, CellHarness
from tests.leaks import unmarked

MACHINES = default_machines(run_time=0.3, measure_time=0.3)  # wc1, wc2 (dummy mills), cmm_wc (CMM simulator)
# Where the browser tests keep their screenshots: var/test-artifacts/web/ of the checkout (git-ignored).
ARTIFACTS = Path(__file__).parents[2] / "var" / "test-artifacts" / "web"
PASSWORD = {"ada": "admin-pass-1", "vera": "viewer-pass-1", "otto": "operator-pass-1", "emma": "engineer-pass-1"}
ROLE = {"ada": "admin", "vera": "viewer", "otto": "operator", "emma": "engineer"}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def gwc_as(cell: CellHarness, login: str | None, *args: str, stdin: str = "") -> subprocess.CompletedProcess[str]:
    """A `gwc` command as unix login `login` would run it through sudo (SUDO_USER), or as root itself."""
    env = cell.env()
    env.pop("SUDO_USER", None)
    if login:
        env["SUDO_USER"] = login
    return subprocess.run(
        [sys.executable, "-m", "gwc", *args], env=env, input=stdin, capture_output=True, text=True, timeout=60
    )


@contextlib.contextmanager
def web_cell(xprocess: Any, pg_cluster: Any, **web: Any) -> Iterator[tuple[CellHarness, str]]:
    """A private cell with its web module and OPC UA gateway up and a user of each role (unix logins of
    the same names; root is `ada`, the admin). Yields the cell and the web's base URL."""
    name = f"gwc_t_{uuid.uuid4().hex[:12]}"
    with pg_cluster.admin() as conn:
        conn.execute(
            sql.SQL("create database {} template {}").format(sql.Identifier(name), sql.Identifier(pg_cluster.template))
        )
    var = Path(tempfile.mkdtemp(prefix="gwc-web-"))
    port = free_port()
    cell = CellHarness(
        xprocess,
        var,
        pg_cluster.url(name),
        machines=MACHINES,
        modules=(*SERVERS, "web", "opcua"),
        sections={
            "web": {"listen": f"127.0.0.1:{port}", "lockout_s": 3.0, **web},
            "opcua": {"endpoint": f"opc.tcp://127.0.0.1:{free_port()}/gwc/", "anonymous": False, "refresh": 2.0},
        },
    )
    try:
        with db.connect(cell.cfg, role="hi") as conn:  # as `gwc user add` does (tests/unit/test_users.py runs it)
            for user, password in PASSWORD.items():
                unix = "root" if user == "ada" else user
                store.add_user(conn, user, Role[ROLE[user]], hash_password(password), unix, "test")
        cell.start_servers()
        for m in MACHINES:
            cell.start_machine_processes(m["id"])
        cell.start("web")  # the OPC UA gateway is started by the test that needs it (start_gateway)
        yield cell, f"https://127.0.0.1:{port}"
    finally:
        cell.close()
        with pg_cluster.admin() as conn:
            conn.execute(sql.SQL("drop database if exists {} with (force)").format(sql.Identifier(name)))
        subprocess.run(["rm", "-rf", str(var)], check=False)


def start_gateway(cell: CellHarness) -> None:
    """The OPC UA gateway of the web cell, once: its address space takes seconds to build (49 s at load 50).
    It is the module's cell's, stopped with it: started without the test's leak mark."""
    with unmarked():
        cell.start("opcua", timeout=120)


def client(base: str) -> httpx.Client:
    """An HTTPS client that trusts the cell's self-signed certificate (the test checks it is HTTPS)."""
    return httpx.Client(base_url=base, verify=False, timeout=15.0)


def logged_in(base: str, user: str) -> tuple[httpx.Client, str]:
    c = client(base)
    r = c.post("/api/login", json={"user": user, "password": PASSWORD[user]})
    assert r.status_code == 200, r.text
    return c, r.json()["csrf"]


def audit_rows(cell: CellHarness, user: str | None = None) -> list[tuple[Any, ...]]:
    return cell.query(
        "select user_name, role, door, action, target, outcome, note from audit_trail "
        "where %s::text is null or user_name = %s order by audit_no",
        user,
        user,
    )
