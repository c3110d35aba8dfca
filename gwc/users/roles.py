"""The one table of who may do what (docs/users.md), consulted at every door: the web, the console,
the `gwc` commands and OPC UA. A door names the action (an `Action`) and asks `check`; a refusal is
raised (`Forbidden`), with a message naming the roles that may.

Roles are ranked: each may do what the one below it may, and more. The table gives each action the
lowest role that may do it.
"""

from __future__ import annotations

import enum

from gwc.errors import Forbidden


class Role(enum.IntEnum):
    """A person's role, lowest first."""

    viewer = 1  # looks at everything, changes nothing
    operator = 2  # runs production: machines, alarms, orders, lots
    engineer = 3  # changes how the cell works: recipes, requests, reservations, alarm descriptions
    admin = 4  # people and the audit trail

    @classmethod
    def parse(cls, name: str) -> Role:
        try:
            return cls[name]
        except KeyError:
            raise ValueError(f"no role {name!r} (roles: {', '.join(r.name for r in cls)})") from None


class Action(enum.StrEnum):
    """What a person may ask the cell to do, by any door."""

    VIEW = "view"
    MACHINE_START = "machine.start"
    MACHINE_STOP = "machine.stop"
    ALARM_CLEAR = "alarm.clear"
    ORDER_ENTER = "order.enter"
    LOT_IMPORT = "lot.import"
    LOT_EXPORT = "lot.export"
    LOT_RELEASE = "lot.release"
    DOWNTIME_REASON = "downtime.reason"
    REQUEST_CANCEL = "request.cancel"
    MACHINE_UNRESERVE = "machine.unreserve"
    MACHINE_MAINTAINED = "machine.maintained"
    LOT_CHANGE = "lot.change"  # divide, merge, destroy
    RECIPE_ADD = "recipe.add"
    RECIPE_APPROVE = "recipe.approve"
    ALARM_DESCRIBE = "alarm.describe"
    USER_MANAGE = "user.manage"
    AUDIT_READ = "audit.read"


# The table (docs/users.md prints it): the lowest role that may do each action.
LOWEST: dict[Action, Role] = {
    Action.VIEW: Role.viewer,
    Action.MACHINE_START: Role.operator,
    Action.MACHINE_STOP: Role.operator,
    Action.ALARM_CLEAR: Role.operator,
    Action.ORDER_ENTER: Role.operator,
    Action.LOT_IMPORT: Role.operator,
    Action.LOT_EXPORT: Role.operator,
    Action.LOT_RELEASE: Role.operator,
    Action.DOWNTIME_REASON: Role.operator,
    Action.REQUEST_CANCEL: Role.engineer,
    Action.MACHINE_UNRESERVE: Role.engineer,
    Action.MACHINE_MAINTAINED: Role.engineer,
    Action.LOT_CHANGE: Role.engineer,
    Action.RECIPE_ADD: Role.engineer,
    Action.RECIPE_APPROVE: Role.engineer,
    Action.ALARM_DESCRIBE: Role.engineer,
    Action.USER_MANAGE: Role.admin,
    Action.AUDIT_READ: Role.admin,
}

# What the words mean to a person, for refusals and the docs.
SAYS: dict[Action, str] = {
    Action.VIEW: "look at the cell",
    Action.MACHINE_START: "start a machine",
    Action.MACHINE_STOP: "stop a machine",
    Action.ALARM_CLEAR: "clear an alarm",
    Action.ORDER_ENTER: "enter a work order",
    Action.LOT_IMPORT: "import a lot",
    Action.LOT_EXPORT: "export a lot",
    Action.LOT_RELEASE: "release a held entity",
    Action.DOWNTIME_REASON: "give a downtime its reason",
    Action.REQUEST_CANCEL: "cancel a machine request",
    Action.MACHINE_UNRESERVE: "unreserve a machine",
    Action.MACHINE_MAINTAINED: (
        "record a machine's maintenance (`gwc machine maintenance-done`, `gwc tool change`: a worn tool changed)"
    ),
    Action.LOT_CHANGE: "divide, merge or destroy lots",
    Action.RECIPE_ADD: "add a recipe version",
    Action.RECIPE_APPROVE: "approve a recipe version",
    Action.ALARM_DESCRIBE: "describe an alarm and its actions",
    Action.USER_MANAGE: "add, remove or change users",
    Action.AUDIT_READ: "read the audit trail",
}


def allowed(role: Role, action: Action) -> bool:
    return role >= LOWEST[action]


def roles_for(action: Action) -> list[Role]:
    return [r for r in Role if allowed(r, action)]


def check(user: str, role: Role, action: Action) -> None:
    """Forbidden unless `role` may do `action`, with a message a person can act on."""
    if not allowed(role, action):
        may = ", ".join(r.name for r in roles_for(action))
        raise Forbidden(f"{user} ({role.name}) may not {SAYS[action]}: only {may} may")


def table_markdown() -> str:
    """The table as docs/users.md shows it (tests compare the two)."""
    head = "| action | what | " + " | ".join(r.name for r in Role) + " |"
    rule = "|---|---|" + "---|" * len(Role)
    rows = [
        f"| `{a.value}` | {SAYS[a]} | " + " | ".join("yes" if allowed(r, a) else "-" for r in Role) + " |"
        for a in Action
    ]
    return "\n".join([head, rule, *rows])
