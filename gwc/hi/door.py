"""The `gwc` command as a door (docs/users.md): each command that acts on the cell is one action of
the role table; the person running it is their unix login mapped to a cell user (gwc.users.doors),
refused before anything is done when their role may not, and every act is appended to the audit
trail with its outcome. Commands that only look are not checked (whoever may run `gwc` holds the
cell key and may read the cell)."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager

import click

from gwc.client.session import context, hi_conn
from gwc.errors import GwcError
from gwc.users import Action, Person, identify_unix, refuse_unless
from gwc.users.doors import audit

# A command line's first words -> the action it is.
COMMAND_ACTIONS: dict[tuple[str, ...], Action] = {
    ("machine", "start"): Action.MACHINE_START,
    ("machine", "stop"): Action.MACHINE_STOP,
    ("machine", "maintenance-done"): Action.MACHINE_MAINTAINED,
    ("tool", "change"): Action.MACHINE_MAINTAINED,  # a worn tool changed (docs/quality.md): a maintenance
    ("alarm", "clear"): Action.ALARM_CLEAR,
    ("alarm", "describe"): Action.ALARM_DESCRIBE,
    ("order", "new"): Action.ORDER_ENTER,
    ("customer", "add"): Action.ORDER_ENTER,
    ("import",): Action.LOT_IMPORT,
    ("export",): Action.LOT_EXPORT,
    ("release",): Action.LOT_RELEASE,
    ("lots", "divide"): Action.LOT_CHANGE,
    ("lots", "merge"): Action.LOT_CHANGE,
    ("lots", "destroy"): Action.LOT_CHANGE,
    ("cancel",): Action.REQUEST_CANCEL,
    ("unreserve",): Action.MACHINE_UNRESERVE,
    ("recipe", "add"): Action.RECIPE_ADD,
    ("recipe", "approve"): Action.RECIPE_APPROVE,
    ("script", "register"): Action.RECIPE_ADD,
    ("downtime", "reason"): Action.DOWNTIME_REASON,
}


def action_of(tokens: Sequence[str]) -> tuple[Action, str] | None:
    """The action a command line is, and its target (the rest of its words), or None."""
    words = list(tokens)
    if "--help" in words or "-h" in words:
        return None
    for n in (2, 1):
        action = COMMAND_ACTIONS.get(tuple(words[:n]))
        if action is not None:
            return action, " ".join(words[n:])[:500]
    return None


@contextmanager
def gwc_door(tokens: Sequence[str]) -> Iterator[Person | None]:
    """Around one `gwc` command: checked and audited if it acts (else nothing is done)."""
    found = action_of(tokens)
    if found is None:
        yield None
        return
    action, target = found
    cfg, log = context()
    with hi_conn(cfg, log) as conn:
        who = identify_unix(conn, "gwc")
        refuse_unless(conn, who, action, target, log)
    outcome, note = "failed", ""
    try:
        yield who
        outcome = "ok"
    except click.exceptions.Exit as e:
        outcome = "ok" if e.exit_code == 0 else "failed"
        raise
    except (GwcError, click.ClickException) as e:
        note = str(e)
        raise
    except BaseException as e:
        note = f"{type(e).__name__}: {e}"
        raise
    finally:
        with hi_conn(cfg, log) as conn:
            audit(conn, who, action, target, outcome, note)
