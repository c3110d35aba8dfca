"""The gateway as a door of the cell (docs/users.md). A session's user is an [opcua] users entry (an
MES's account in cell.toml: role engineer, every method the gateway has, as before users) or a cell
user (name and password, argon2, their own role). Each method call is checked against the role table
before it runs, refused with BadUserAccessDenied (logged and audited) when the role may not, and its
outcome appended to the audit trail in the caller's name.

asyncua checks a request (GatewayRules.check_validity) and then runs its calls in the same task, so
the caller found at the check is handed to the method's outcome through a context variable.
"""

from __future__ import annotations

import asyncio
import contextvars
import logging
import threading
from collections.abc import Sequence
from typing import Any

import psycopg
from asyncua import ua

from gwc import db
from gwc.config import Config
from gwc.errors import GwcError
from gwc.users import Action, Person, Role, store
from gwc.users.doors import audit
from gwc.users.passwords import verify
from gwc.users.roles import allowed

# A method's name (the last part of its node id in the cell's namespace) -> its action.
METHOD_ACTIONS = {
    "Start": Action.MACHINE_START,
    "Stop": Action.MACHINE_STOP,
    "Unreserve": Action.MACHINE_UNRESERVE,
    "MaintenanceDone": Action.MACHINE_MAINTAINED,
    "SetDowntimeReason": Action.DOWNTIME_REASON,
    "EnterWorkOrder": Action.ORDER_ENTER,
    "ImportLot": Action.LOT_IMPORT,
    "ExportLot": Action.LOT_EXPORT,
    "CancelRequest": Action.REQUEST_CANCEL,
    "ClearAlarm": Action.ALARM_CLEAR,
}
CALLER: contextvars.ContextVar[tuple[Person, list[tuple[Action, str]]] | None] = contextvars.ContextVar(
    "gwc_opcua_caller", default=None
)


class OpcuaDoor:
    def __init__(self, cfg: Config, log: logging.Logger) -> None:
        self.cfg = cfg
        self.log = log
        self.roles: dict[str, Role] = {}  # session user name -> role, set at login
        self._conn: psycopg.Connection[Any] | None = None
        self._lock = threading.Lock()

    def _run(self, fn: Any) -> Any:
        with self._lock:
            try:
                if self._conn is None or self._conn.closed:
                    self._conn = db.connect(self.cfg, role="opcua", log=self.log, attempts=1)
                return fn(self._conn)
            except (psycopg.Error, GwcError) as e:
                if self._conn is not None:
                    self._conn.close()
                self._conn = None
                self.log.error("OPC UA door: the database: %s", e)
                return None

    def cell_login(self, name: str, password: str) -> Role | None:
        """A cell user's role if the password is theirs (blocking: at session activation)."""
        user = self._run(lambda c: store.get_user(c, name))
        if not verify(user.password_hash if user else None, password) or user is None:
            return None
        return Role(user.role)

    def check(self, name: str, method_ids: Sequence[ua.NodeId]) -> bool:
        """The rule for one Call request: every method it calls allowed for the user's role; a refusal
        is logged and audited. The caller is handed to the outcome (CALLER)."""
        role = self.roles.get(name, Role.engineer)  # a certificate user: as an [opcua] users entry
        who = Person(name, role, "opcua")
        acts = []
        for mid in method_ids:
            ident = mid.Identifier if isinstance(mid.Identifier, str) else ""
            method = ident.rsplit("/", 1)[-1]
            action = METHOD_ACTIONS.get(method)
            if action is None:
                continue  # Acknowledge, Confirm, ConditionRefresh: they change nothing in the cell
            target = ident.rsplit("/", 1)[0]
            if not allowed(role, action):
                why = (
                    f"{name} ({role.name}) may not call {method}: only "
                    + ", ".join(r.name for r in Role if allowed(r, action))
                    + " may"
                )
                self.log.warning("OPC UA call of %s refused: %s", ident, why)
                self._run(lambda c, a=action, t=target, w=why: audit(c, who, a, t, "refused", w))
                return False
            acts.append((action, target))
        CALLER.set((who, acts) if acts else None)
        return True

    async def done(self, result: ua.CallMethodResult) -> None:
        """The outcome of the method the caller called, to the audit trail."""
        caller = CALLER.get()
        if caller is None:
            return
        who, acts = caller
        good = result.StatusCode is None or result.StatusCode.is_good()
        code = result.OutputArguments[0].Value if result.OutputArguments else ""
        note = result.OutputArguments[1].Value if len(result.OutputArguments) > 1 else str(result.StatusCode)
        ok = good and code in ("ACK_OK", "")
        for action, target in acts:
            await asyncio.to_thread(
                self._run, lambda c, a=action, t=target: audit(c, who, a, t, "ok" if ok else "failed", f"{code} {note}")
            )

    def close(self) -> None:
        with self._lock:
            if self._conn is not None:
                self._conn.close()
