"""The role table walked door by door (docs/users.md): for every action each door offers, one call as
that door spells it, made by a user of every role. Each call names an object nothing has (machine
`nosuch`, alarm 999, entity 999999, ...) wherever one exists, so that a role that may passes the door
and the owning module answers with a domain error (or the act is done, harmlessly), and a role that
may not is refused at the door: a clear message and an audit row `refused`.

What a call answered is one `Answer`: refused (the door's role check said no) or not, and the text.
The test then reads the audit trail: for each door, user and action, the last row is `refused`
exactly when the role may not, and a refusal's note says who may.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from click.testing import CliRunner

from gwc.cli import cli
from gwc.console.link import CellLink
from gwc.log import open_log
from gwc.users import Action
from tests.e2e.webkit import PASSWORD, logged_in
from tests.harness import CellHarness

NOSUCH_ENTITY = 999_999


@dataclass(frozen=True)
class Answer:
    refused: bool
    text: str


# ------------------------------------------------------------------------------------------- the web

# (method, path, JSON body) for each action the web offers (gwc.web.app.WEB_ACTIONS)
WEB_CALLS: dict[Action, tuple[str, str, Any]] = {
    Action.MACHINE_START: ("POST", "/api/machines/nosuch/start", None),
    Action.MACHINE_STOP: ("POST", "/api/machines/nosuch/stop", None),
    Action.ALARM_CLEAR: ("POST", "/api/alarms/999/clear", None),
    Action.ORDER_ENTER: ("POST", "/api/orders", {"customer": "", "items": ""}),
    Action.LOT_IMPORT: ("POST", f"/api/lots/{NOSUCH_ENTITY}/import", None),
    Action.LOT_EXPORT: ("POST", f"/api/lots/{NOSUCH_ENTITY}/export", None),
    Action.LOT_RELEASE: ("POST", f"/api/lots/{NOSUCH_ENTITY}/release", {"decision": "retry"}),
    Action.DOWNTIME_REASON: ("POST", f"/api/downtime/{NOSUCH_ENTITY}/reason", {"reason": "breakdown"}),
    Action.RECIPE_APPROVE: ("POST", "/api/recipes/nosuch_recipe/approve", {}),
    Action.AUDIT_READ: ("GET", "/api/audit?limit=1", None),
    Action.VIEW: ("GET", "/api/machines", None),
}


def walk_web(base: str, users: list[str]) -> dict[tuple[str, Action], Answer]:
    out = {}
    for user in users:
        c, csrf = logged_in(base, user)
        with contextlib.closing(c):
            for action, (method, path, body) in WEB_CALLS.items():
                r = c.request(method, path, headers={"X-CSRF-Token": csrf}, json=body)
                text = r.json().get("error", "") if r.status_code >= 400 else "ok"
                assert r.status_code not in (401, 404, 405, 415), (user, action, r.status_code, text)
                out[(user, action)] = Answer(r.status_code == 403, text)
    return out


# ---------------------------------------------------------------------------------------- `gwc`

# Each command line of gwc.hi.door.COMMAND_ACTIONS, with arguments that name nothing the cell has.
GWC_CALLS: list[tuple[Action, tuple[str, ...]]] = [
    (Action.MACHINE_START, ("machine", "start", "nosuch")),
    (Action.MACHINE_STOP, ("machine", "stop", "nosuch")),
    (Action.MACHINE_MAINTAINED, ("machine", "maintenance-done", "nosuch")),
    (Action.MACHINE_MAINTAINED, ("tool", "change", "nosuch")),
    (Action.ALARM_CLEAR, ("alarm", "clear", "999")),
    (Action.ALARM_DESCRIBE, ("alarm", "describe", "DOOR_TEST", "--text", "the door test's alarm")),
    (Action.ORDER_ENTER, ("order", "new", "--customer", "NOSUCH", "nosuch_product=1")),
    (Action.ORDER_ENTER, ("customer", "add", "DOOR_TEST", "--name", "The door test")),
    (Action.LOT_IMPORT, ("import", str(NOSUCH_ENTITY))),
    (Action.LOT_EXPORT, ("export", str(NOSUCH_ENTITY))),
    (Action.LOT_RELEASE, ("release", str(NOSUCH_ENTITY), "--decision", "retry")),
    (Action.LOT_CHANGE, ("lots", "divide", str(NOSUCH_ENTITY))),
    (Action.LOT_CHANGE, ("lots", "merge", str(NOSUCH_ENTITY), str(NOSUCH_ENTITY + 1))),
    (Action.LOT_CHANGE, ("lots", "destroy", str(NOSUCH_ENTITY))),
    (Action.REQUEST_CANCEL, ("cancel", "999")),
    (Action.MACHINE_UNRESERVE, ("unreserve", "nosuch")),
    (Action.RECIPE_ADD, ("recipe", "add", "nosuch_recipe", "/nonexistent/recipe.txt")),
    (Action.RECIPE_ADD, ("script", "register", "nosuch_script", "/nonexistent/script.py")),
    (Action.RECIPE_APPROVE, ("recipe", "approve", "nosuch_recipe")),
    (Action.DOWNTIME_REASON, ("downtime", "reason", str(NOSUCH_ENTITY), "breakdown")),
    (Action.USER_MANAGE, ("user", "remove", "nosuch_user")),
    (Action.AUDIT_READ, ("audit", "--since", "1s")),
]
REFUSED_EXIT = 8  # gwc.errors.Forbidden's


def walk_gwc(cell: CellHarness, users: list[str]) -> dict[tuple[str, tuple[str, ...]], Answer]:
    """Each command line as each unix login would run it through sudo (SUDO_USER; ada is root itself), in
    this process (click's runner: the same cli, door and client code as `python -m gwc`, without a
    hundred interpreters)."""
    runner = CliRunner()
    out = {}
    for user in users:
        env = {**cell.env(), "SUDO_USER": None if user == "ada" else user}
        for _, args in GWC_CALLS:
            done = runner.invoke(cli, list(args), env=env)
            out[(user, args)] = Answer(done.exit_code == REFUSED_EXIT, done.output.strip())
    return out


# ---------------------------------------------------------------------------------------- the console

# Each act of gwc.console.link.CellLink the role table names, on nothing the cell has.
CONSOLE_CALLS: dict[Action, Callable[[CellLink], Any]] = {
    Action.MACHINE_START: lambda link: link.start_machine("nosuch"),
    Action.MACHINE_STOP: lambda link: link.stop_machine("nosuch"),
    Action.MACHINE_MAINTAINED: lambda link: link.maintenance_done("nosuch"),
    Action.ALARM_CLEAR: lambda link: link.clear_alarm(999),
    Action.REQUEST_CANCEL: lambda link: link.cancel_request(999),
    Action.MACHINE_UNRESERVE: lambda link: link.unreserve_machine("nosuch"),
    Action.ORDER_ENTER: lambda link: link.enter_order("NOSUCH", [("nosuch_product", 1)]),
    Action.LOT_IMPORT: lambda link: link.decide(NOSUCH_ENTITY, "import"),
    Action.LOT_EXPORT: lambda link: link.decide(NOSUCH_ENTITY, "export"),
}


def walk_console(cell: CellHarness, users: list[str], monkeypatch: Any) -> dict[tuple[str, Action], Answer]:
    """The console's link, as `gwc console` acts (the person found from the login, as for gwc)."""
    out = {}
    for user in users:
        monkeypatch.setenv("SUDO_USER", "root" if user == "ada" else user)
        link = CellLink(cell.cfg, open_log("console", cell.cfg.log_dir, "note"))
        link.open()
        try:
            for action, call in CONSOLE_CALLS.items():
                answer = call(link)
                out[(user, action)] = Answer("may not" in answer.text, answer.text)
        finally:
            link.close()
    monkeypatch.delenv("SUDO_USER")
    return out


# ---------------------------------------------------------------------------------------- OPC UA


# Each method of gwc.opcua.door.METHOD_ACTIONS: (node id in the cell's namespace, arguments). A
# machine's methods are called on a real machine: wc1 (Start: it is Idle already), wc2 (Stop: it is
# stopped already), Unreserve (nobody holds it), MaintenanceDone (a count started again: harmless),
# SetDowntimeReason (a reason no tree has).
def opcua_calls() -> dict[str, tuple[str, list[tuple[Any, str]]]]:
    return {
        "Start": ("machines/wc1/Start", []),
        "Stop": ("machines/wc2/Stop", []),
        "Unreserve": ("machines/wc1/Unreserve", [(False, "Boolean")]),
        "MaintenanceDone": ("machines/wc1/MaintenanceDone", []),
        "SetDowntimeReason": ("machines/wc1/SetDowntimeReason", [("no such reason", "String")]),
        "EnterWorkOrder": ("cell/EnterWorkOrder", [("NOSUCH", "String"), ("nosuch_product=1", "String"), (0, "Int32")]),
        "ImportLot": ("cell/ImportLot", [(NOSUCH_ENTITY, "Int64")]),
        "ExportLot": ("cell/ExportLot", [(NOSUCH_ENTITY, "Int64")]),
        "CancelRequest": ("cell/CancelRequest", [(999, "Int64")]),
        "ClearAlarm": ("cell/ClearAlarm", [(999, "Int64")]),
    }


def walk_opcua(cell: CellHarness, certs: Path, users: list[str]) -> dict[tuple[str, str], Answer]:
    """Every method by each cell user over a SignAndEncrypt channel: refused is BadUserAccessDenied."""
    from asyncua import Client, ua
    from asyncua.crypto.cert_gen import setup_self_signed_certificate
    from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
    from cryptography.x509.oid import ExtendedKeyUsageOID

    endpoint = cell.cfg.raw["opcua"]["endpoint"]
    out: dict[tuple[str, str], Answer] = {}

    async def run() -> None:
        cert, key = certs / "client-cert.der", certs / "client-key.pem"
        await setup_self_signed_certificate(
            key, cert, "urn:gwc:test:client", "localhost", [ExtendedKeyUsageOID.CLIENT_AUTH], {"commonName": "t"}
        )
        for user in users:
            client = Client(endpoint, timeout=30)
            client.application_uri = "urn:gwc:test:client"
            await client.set_security(
                SecurityPolicyBasic256Sha256, str(cert), str(key), mode=ua.MessageSecurityMode.SignAndEncrypt
            )
            client.set_user(user)
            client.set_password(PASSWORD[user])
            await client.connect()
            try:
                ns = await client.get_namespace_index("urn:gwc:cell")
                for method, (node, args) in opcua_calls().items():
                    parent = ua.NodeId(node.rsplit("/", 1)[0], ns)
                    variants = [ua.Variant(v, getattr(ua.VariantType, t)) for v, t in args]
                    try:
                        await client.get_node(parent).call_method(ua.NodeId(node, ns), *variants)
                        out[(user, method)] = Answer(False, "Good")
                    except ua.UaStatusCodeError as e:
                        name = type(e).__name__
                        out[(user, method)] = Answer(name == "BadUserAccessDenied", f"{name}: {e}")
            finally:
                await client.disconnect()

    asyncio.run(run())
    return out
