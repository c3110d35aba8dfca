"""Users, the role table and the audit trail on a fresh database: what the doors stand on."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import psycopg
import pytest

from gwc import db
from gwc.config import Config
from gwc.errors import Forbidden, NotAuthenticated
from gwc.hi.door import action_of
from gwc.users import Action, Role, act, check, identify_unix, login, store
from gwc.users.passwords import hash_password, verify
from gwc.users.roles import table_markdown

DOCS = Path(__file__).parents[2] / "docs" / "users.md"


def test_the_role_table_in_the_docs_is_the_one_the_doors_consult() -> None:
    assert table_markdown() in DOCS.read_text(), "docs/users.md's table differs: paste gwc.users.roles.table_markdown()"


def doors_markdown() -> str:
    """Which door offers each action, from the doors' own tables: the web's routes (WEB_ACTIONS), the
    `gwc` command lines (COMMAND_ACTIONS, and `gwc user`, `gwc audit`), the console's acts (its link's
    `Action.X`), the OPC UA methods (METHOD_ACTIONS)."""
    import re

    from gwc.hi.door import COMMAND_ACTIONS
    from gwc.opcua.door import METHOD_ACTIONS
    from gwc.web.app import WEB_ACTIONS

    link = (Path(__file__).parents[2] / "gwc" / "console" / "link.py").read_text()
    console = {Action[n] for n in re.findall(r"\bAction\.([A-Z_]+)\b", link)}
    gwc: dict[Action, list[str]] = {}
    for words, a in COMMAND_ACTIONS.items():
        gwc.setdefault(a, []).append("gwc " + " ".join(words))
    gwc.setdefault(Action.USER_MANAGE, []).append("gwc user add/remove/passwd/role")
    gwc.setdefault(Action.AUDIT_READ, []).append("gwc audit")

    def cell(items: list[str]) -> str:
        return ", ".join(f"`{i}`" for i in items) or "-"

    rows = ["| action | web | `gwc` | console | OPC UA |", "|---|---|---|---|---|"]
    for a in Action:
        web = [route for route, x in WEB_ACTIONS.items() if x is a]
        if a is Action.VIEW:
            web = ["GET /api/..."]
        opcua = [m for m, x in METHOD_ACTIONS.items() if x is a]
        rows.append(
            f"| `{a.value}` | {cell(web)} | {cell(gwc.get(a, []))} | {'yes' if a in console else '-'} | {cell(opcua)} |"
        )
    return "\n".join(rows)


def test_the_doors_table_in_the_docs_is_the_doors_own() -> None:
    table = doors_markdown()
    assert table in DOCS.read_text(), "docs/users.md's table of doors differs; it should read:\n" + table


def test_each_role_may_what_the_one_below_may_and_a_refusal_names_who_may() -> None:
    check("v", Role.viewer, Action.VIEW)
    check("o", Role.operator, Action.MACHINE_START)
    with pytest.raises(Forbidden, match=r"v \(viewer\) may not start a machine: only operator, engineer, admin may"):
        check("v", Role.viewer, Action.MACHINE_START)
    with pytest.raises(Forbidden, match="only admin may"):
        check("e", Role.engineer, Action.AUDIT_READ)


def test_passwords_are_salted_argon2_and_checked() -> None:
    a, b = hash_password("correct horse"), hash_password("correct horse")
    assert a.startswith("$argon2id$") and a != b
    assert verify(a, "correct horse") and not verify(a, "wrong horse!") and not verify(None, "correct horse")
    with pytest.raises(ValueError, match="8 characters"):
        hash_password("short")


def test_the_cli_loads_the_door_for_every_command_that_acts() -> None:
    from gwc.cli import ACTING
    from gwc.hi.door import COMMAND_ACTIONS

    assert {words[0] for words in COMMAND_ACTIONS} == ACTING


def test_a_command_line_is_its_action_and_target() -> None:
    assert action_of(["machine", "start", "wc1"]) == (Action.MACHINE_START, "wc1")
    assert action_of(["import", "--all"]) == (Action.LOT_IMPORT, "--all")
    assert action_of(["machine", "status"]) is None
    assert action_of(["machine", "start", "--help"]) is None


def hi(cfg: Config) -> psycopg.Connection[Any]:
    return db.connect(cfg, role="hi")


def test_users_map_unix_logins_and_an_empty_cell_is_open(cell_config: Config, monkeypatch: Any) -> None:
    with hi(cell_config) as conn:
        monkeypatch.setattr(os, "getuid", lambda: 0)
        monkeypatch.setenv("SUDO_USER", "alice")
        open_person = identify_unix(conn, "gwc")
        assert (open_person.name, open_person.role, open_person.managed) == ("alice", Role.admin, False)
        store.add_user(conn, "ann", Role.operator, hash_password("password-1"), "alice", "test")
        store.add_user(conn, "bob", Role.viewer, hash_password("password-2"), None, "test")
        assert identify_unix(conn, "gwc").name == "ann"
        monkeypatch.setenv("SUDO_USER", "bob")
        assert identify_unix(conn, "gwc").role == Role.viewer
        monkeypatch.setenv("SUDO_USER", "carol")
        with pytest.raises(NotAuthenticated, match="unix user carol is no user of this cell"):
            identify_unix(conn, "gwc")
        assert login(conn, "ann", "password-1", "web", "1.2.3.4").role == Role.operator
        for name, password in (("ann", "password-2"), ("nobody", "password-1")):
            with pytest.raises(NotAuthenticated, match="wrong user name or password"):
                login(conn, name, password, "web", "1.2.3.4")


def test_every_act_is_audited_and_the_trail_cannot_be_changed(cell_config: Config, database_url: str) -> None:
    with hi(cell_config) as conn:
        store.add_user(conn, "vic", Role.viewer, hash_password("password-3"), None, "test")
        vic = login(conn, "vic", "password-3", "web", "10.0.0.9")
        with pytest.raises(Forbidden), act(conn, vic, Action.MACHINE_STOP, "wc1"):
            pytest.fail("a viewer's act ran")
        with act(conn, vic, Action.VIEW, "machines") as notes:
            notes.append("looked")
        rows = store.audit_rows(conn, user="vic")
        assert [(r.action, r.target, r.outcome, r.door, r.address) for r in rows] == [
            ("machine.stop", "wc1", "refused", "web", "10.0.0.9"),
            ("view", "machines", "ok", "web", "10.0.0.9"),
        ]
        assert "may not stop a machine" in rows[0].note
        for sql in ("update audit_trail set outcome = 'ok'", "delete from audit_trail", "truncate audit_trail"):
            with pytest.raises(psycopg.errors.InsufficientPrivilege):
                conn.execute(sql)
            conn.rollback()
    with psycopg.connect(database_url) as su:  # the cluster's superuser: the trigger refuses it too
        for sql in ("update audit_trail set outcome = 'ok'", "delete from audit_trail", "truncate audit_trail"):
            with pytest.raises(psycopg.errors.InsufficientPrivilege, match="append-only"):
                su.execute(sql)
            su.rollback()
        assert su.execute("select count(*) from audit_trail").fetchone() == (2,)


def gwc(
    cfg: Config, database_url: str, *args: str, stdin: str = "", sudo: str = ""
) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, GWC_CONFIG=str(cfg.path), GWC_VAR=str(cfg.var), GWC_DATABASE_URL=database_url)
    env.pop("SUDO_USER", None)
    if sudo:
        env["SUDO_USER"] = sudo
    return subprocess.run(
        [sys.executable, "-m", "gwc", *args], env=env, input=stdin, capture_output=True, text=True, timeout=60
    )


def test_gwc_user_and_gwc_audit_for_admins_refused_to_others(cell_config: Config, database_url: str) -> None:
    if os.getuid() != 0:
        pytest.skip("maps logins through SUDO_USER, which only root's commands read")
    g = lambda *a, **k: gwc(cell_config, database_url, *a, **k)
    first = g("user", "add", "root-admin", "--role", "admin", "--unix", "root", stdin="admin-pass\n")
    assert first.returncode == 0, first.stderr  # an open cell: anyone adds the first user
    assert g("user", "add", "ola", "--role", "operator", stdin="op-pass-1\n").returncode == 0
    short = g("user", "add", "x", "--role", "viewer", stdin="short\n")
    assert short.returncode != 0 and "8 characters" in short.stderr
    listed = g("user", "list", "--json")
    assert '"ola"' in listed.stdout and "argon2" not in listed.stdout
    refused = g("user", "add", "eve", "--role", "admin", sudo="ola", stdin="eve-pass-1\n")
    assert refused.returncode == 8 and "ola (operator) may not add, remove or change users" in refused.stderr
    stranger = g("machine", "stop", "wc1", sudo="mallory")
    assert stranger.returncode == 8 and "unix user mallory is no user of this cell" in stranger.stderr
    assert g("audit", sudo="ola").returncode == 8
    trail = g("audit", "--json")
    assert trail.returncode == 0, trail.stderr
    assert '"refused"' in trail.stdout and '"ola"' in trail.stdout
    mine = json.loads(g("audit", "--user", "ola", "--since", "1h", "--json").stdout)
    assert {r["user_name"] for r in mine} == {"ola"} and {r["outcome"] for r in mine} == {"refused"}
