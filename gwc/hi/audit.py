"""The audit trail: `gwc audit [--since T] [--user U] [--json]` (admin; docs/users.md)."""

from __future__ import annotations

import click

from gwc.client.record import parse_when
from gwc.client.session import hi_conn
from gwc.errors import GwcError
from gwc.hi import context, json_option, table
from gwc.users import Action, act, identify_unix, store

COLUMNS = ["audit_no", "at", "user_name", "role", "door", "address", "action", "target", "outcome", "note"]


@click.command("audit")
@click.option("--since", default=None, help="From when: YYYY-MM-DD [HH:MM], today, 8h, ... (default: everything).")
@click.option("--user", default=None, help="Only this user's acts.")
@click.option("--limit", default=1000, show_default=True, help="At most this many rows (the newest).")
@json_option
def audit_command(since: str | None, user: str | None, limit: int, as_json: bool) -> None:
    """Every act of a person at any door, allowed or refused: who, role, door, address, what, target,
    outcome, when. Admins only."""
    cfg, log = context()
    try:
        when = parse_when(since, cfg.record.timezone) if since else None
    except (ValueError, GwcError) as e:
        raise click.BadParameter(str(e), param_hint="--since") from None
    with hi_conn(cfg, log) as conn:
        who = identify_unix(conn, "gwc")
        with act(conn, who, Action.AUDIT_READ, user or "", log):
            rows = store.audit_rows(conn, when, user, limit)
    out = [{c: getattr(r, c) for c in COLUMNS} for r in rows]
    for r in out:
        r["at"] = r["at"].strftime("%Y-%m-%d %H:%M:%S.%f")[:-3] if not as_json else r["at"].isoformat()
    table(out, COLUMNS, as_json)


commands = [audit_command]
