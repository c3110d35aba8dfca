"""The Lot Server's database side, in one place: every read and write of LOTS, LOT_ENTITIES and
LOT_STATUS the Lot Server's handlers make (gwc/servers/lot.py parses and answers).

Each function takes the cursor of one transaction (Module.transaction runs it, and runs it again on
a transient failure: nothing here has a side effect outside the database), returns a dataclass, and
raises `Refused` with the ack code and the reason when the request does not fit what the tables
hold. A refusal rolls the step back: nothing it did is kept.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from gwc import db
from gwc.errors import Refused
from gwc.ipc.codes import AckCode, LotState

MAX_QUANTITY = 1000
IN_CELL = frozenset({LotState.IMPORTED, LotState.WAITING_MACHINE, LotState.RUNNING, LotState.COMPLETED})
# An entity in one of these needs no script any more: its death is no failure (CONTRACTS.md).
FINISHED = frozenset({LotState.EXPORTED, LotState.FAILED, LotState.COMPLETED, LotState.WAITING_EXPORT})
ATTACHED = ("product_id", "priority", "work_order_id", "script_id", "script_path")  # an attach's answer


@dataclass(frozen=True)
class NewLot:
    """What CREATE_LOT asks for, checked for form already (the handler's part)."""

    product_id: str
    quantity: int
    lot_id: int | None = None  # more entities of this lot, instead of a new lot
    lot_type: str | None = None
    work_order_id: int | None = None
    owner: str | None = None
    priority: int | None = None
    script_id: str | None = None
    result_params: tuple[str, ...] = ()
    request_id: str | None = None  # the asker's id for this creation: a repeat gets what the first made
    parent: int | None = None  # the entity (a lot script) creating its own children


@dataclass(frozen=True)
class Created:
    """A lot's new entities; `new` False when the request was a repeat and these were made before."""

    lot_id: int
    entity_ids: list[int]
    new: bool


@dataclass(frozen=True)
class Moved:
    """Where an ENTITY_REQ left its entity: its lot, its state, a note, and (attach) its lot's script."""

    lot_id: int | None
    state: LotState | None
    note: str | None = None
    attached: dict[str, Any] = field(default_factory=dict)


def create_lot(cur: Any, new: NewLot) -> Created:
    """A lot (or more of an existing one), one entity per unit, each `created`."""
    if new.request_id:  # asked again (the answer was lost, or we restarted): what the first one made
        cur.execute("select pg_advisory_xact_lock(hashtext(%s))", (new.request_id,))
        made = cur.execute(
            "select lot_id, entity_id from lot_entities where create_request = %s order by unit", (new.request_id,)
        ).fetchall()
        if made:
            return Created(made[0][0], [e for _, e in made], False)
    work_order_id, owner = new.work_order_id, new.owner
    if new.parent is not None:
        work_order_id, owner = _parents_order(cur, new.parent, owner)
    product = cur.execute(
        "select script_id, lot_type from products where product_id = %s", (new.product_id,)
    ).fetchone()
    if product is None:
        raise Refused(AckCode.UNKNOWN, f"no product {new.product_id!r}")
    _must_exist(
        cur, "select 1 from lot_scripts where script_id = %s", new.script_id, f"no lot script {new.script_id!r}"
    )
    _must_exist(
        cur, "select 1 from work_orders where work_order_id = %s", work_order_id, f"no work order {work_order_id}"
    )
    if new.lot_id is not None:
        lot_id, first = _grow_lot(cur, new.lot_id, new.quantity)
    else:
        lot_id, first = db.get_new_max_value(cur, "LOT_ID"), 1
        cur.execute(
            "insert into lots (lot_id, lot_type, work_order_id, product_id, quantity, priority, "
            "owner, script_id, result_params) values (%s, %s, %s, %s, %s, coalesce(%s, 20), %s, %s, %s)",
            (
                lot_id,
                new.lot_type or product[1],
                work_order_id,
                new.product_id,
                new.quantity,
                new.priority,
                owner,
                new.script_id or product[0],
                list(new.result_params),
            ),
        )
    ids = []
    for unit in range(first, first + new.quantity):
        eid = db.get_new_max_value(cur, "ENTITY_ID")
        cur.execute(
            "insert into lot_entities (entity_id, lot_id, unit, create_request, parent_entity_id) "
            "values (%s, %s, %s, %s, %s)",
            (eid, lot_id, unit, new.request_id, new.parent),
        )
        cur.execute("insert into lot_status (entity_id, lot_id, state) values (%s, %s, 'created')", (eid, lot_id))
        ids.append(eid)
    return Created(lot_id, ids, True)


def _parents_order(cur: Any, parent: int, owner: str | None) -> tuple[int | None, str | None]:
    """A lot script's children belong to its own work order (and owner, unless one is given)."""
    of = cur.execute(
        "select s.state, l.work_order_id, l.owner from lot_status s join lot_entities e "
        "using (entity_id) join lots l on l.lot_id = s.lot_id "
        "where s.entity_id = %s and e.destroyed_at is null",
        (parent,),
    ).fetchone()
    if of is None or LotState(of[0]) not in IN_CELL:
        state = of[0] if of else "unknown"
        raise Refused(AckCode.UNKNOWN, f"entity {parent} is {state}: only an entity in the cell starts others")
    return of[1], owner or of[2]


def _must_exist(cur: Any, query: str, key: object, why: str) -> None:
    if key is not None and key != "" and cur.execute(query, (key,)).fetchone() is None:
        raise Refused(AckCode.UNKNOWN, why)


def _grow_lot(cur: Any, lot_id: int, quantity: int) -> tuple[int, int]:
    """`quantity` more units of an existing lot: (its id, the first new unit)."""
    if cur.execute("select lot_id from lots where lot_id = %s for update", (lot_id,)).fetchone() is None:
        raise Refused(AckCode.UNKNOWN, f"no lot {lot_id}")
    first = cur.execute("select coalesce(max(unit), 0) + 1 from lot_entities where lot_id = %s", (lot_id,)).fetchone()[
        0
    ]
    cur.execute("update lots set quantity = quantity + %s where lot_id = %s", (quantity, lot_id))
    return lot_id, first


def move(
    entity_id: int,
    to: LotState,
    came_from: frozenset[LotState],
    reason: str | None,
    keep: bool,
    action: tuple[str, str] | None = None,
) -> db.Statement:
    """An entity (not destroyed) in one of `came_from` moves to `to`, in one statement: the row of its
    lot_id, or None if it was not in one of them (the caller reads why). `reason` replaces the old one,
    or only fills it when `keep`. An operator's `action` (what, by whom) is kept in operator_actions by
    the same statement (the entity's new state goes to entity_state_history by lot_status's trigger)."""
    sql = (
        "update lot_status s set state = %(to)s, updated_at = now(), "
        + ("reason = coalesce(%(reason)s, s.reason) " if keep else "reason = %(reason)s ")
        + "from (select s2.state from lot_status s2 join lot_entities e using (entity_id) "
        "where s2.entity_id = %(e)s and e.destroyed_at is null for update of s2) old "
        "where s.entity_id = %(e)s and old.state = any(%(from)s) returning s.lot_id"
    )
    params = {"to": to.value, "reason": reason, "e": entity_id, "from": [str(x) for x in came_from]}
    if action is None:
        return db.Statement(sql, params)
    return db.Statement(
        f"with moved as ({sql}), act as (insert into operator_actions (entity_id, lot_id, action, by) "
        "select %(e)s, lot_id, %(action)s, %(by)s from moved) select lot_id from moved",
        params | {"action": action[0], "by": action[1]},
    )


def entity_step(
    cur: Any,
    entity_id: int,
    action: str,
    target: LotState | None,
    allowed: frozenset[LotState],
    reason: str | None = None,
    script_pid: int | None = None,
) -> Moved:
    """ENTITY_REQ's step, read first: an attach, a destroy, a state read, or a move `move()` did not
    make (from exported: a new lot, 6.1.1). Refused UNKNOWN for no such entity, NOTNOW (with its lot and
    state) when its state is not one of `allowed`."""
    row = cur.execute(
        "select s.lot_id, s.state, e.destroyed_at from lot_status s "
        "join lot_entities e using (entity_id) where s.entity_id = %s for update of s",
        (entity_id,),
    ).fetchone()
    if row is None or (row[2] is not None and action != "state"):
        raise Refused(AckCode.UNKNOWN, f"no entity {entity_id}" + (" (destroyed)" if row else ""))
    lot_id, state = row[0], LotState(row[1])
    if state not in allowed:
        raise Refused(
            AckCode.NOTNOW, f"entity {entity_id} is {state}: cannot {action}", lot_id=lot_id, state=state.value
        )
    if action == "attach":
        return Moved(lot_id, state, None, attach(cur, entity_id, script_pid))
    if action == "destroy":
        cur.execute("update lot_entities set destroyed_at = now() where entity_id = %s", (entity_id,))
        return Moved(lot_id, state, "destroyed")
    note = "destroyed" if row[2] is not None else None
    if target is not None and target != state:
        if state == LotState.EXPORTED:  # back after an export: a new lot (6.1.1)
            old, lot_id = lot_id, new_lot_for(cur, entity_id, lot_id)
            note = f"re-imported entity: lot {old} -> lot {lot_id}"
        cur.execute(
            "update lot_status set state = %s, reason = %s, updated_at = now() where entity_id = %s",
            (target.value, reason, entity_id),
        )
        state = target
    return Moved(lot_id, state, note)


def attach(cur: Any, entity_id: int, script_pid: int | None) -> dict[str, Any]:
    """Record the entity's script pid; what the script needs of its lot (ATTACHED's fields)."""
    row = cur.execute(
        "update lot_status s set script_pid = %s, updated_at = now() FROM lots l "
        "LEFT JOIN products p USING (product_id) LEFT JOIN lot_scripts ls "
        "ON ls.script_id = coalesce(l.script_id, p.script_id) "
        "WHERE s.entity_id = %s AND l.lot_id = s.lot_id "
        "RETURNING l.product_id, l.priority, l.work_order_id, ls.script_id, ls.path",
        (script_pid, entity_id),
    ).fetchone()
    return dict(zip(ATTACHED, row or (), strict=False))


def new_lot_for(cur: Any, entity_id: int, old_lot: int) -> int:
    """Move an entity into a new lot, a copy of its old one (6.1.1: re-imported, a new lot_id)."""
    lot_id = db.get_new_max_value(cur, "LOT_ID")
    cur.execute(
        "insert into lots (lot_id, lot_type, work_order_id, product_id, quantity, priority, owner, "
        "script_id, result_params) select %s, lot_type, work_order_id, product_id, 1, priority, owner, "
        "script_id, result_params from lots where lot_id = %s",
        (lot_id, old_lot),
    )
    # lot_status names (entity, lot) of lot_entities: out, move the entity, back in, in this one transaction.
    st = cur.execute(
        "delete from lot_status where entity_id = %s returning state, reason, script_pid", (entity_id,)
    ).fetchone()
    cur.execute("update lot_entities set lot_id = %s, unit = 1 where entity_id = %s", (lot_id, entity_id))
    cur.execute(
        "insert into lot_status (entity_id, lot_id, state, reason, script_pid) values (%s, %s, %s, %s, %s)",
        (entity_id, lot_id, *st),
    )
    return lot_id


def record_action(entity_id: int, action: str, by: str, note: str | None) -> db.Statement:
    """An operator's action on an entity done through another module (LOT_ACTION), kept in its history:
    the entity's lot_id; Refused UNKNOWN for no such entity."""

    def into(row: tuple[int] | None) -> int:
        if row is None:
            raise Refused(AckCode.UNKNOWN, f"no entity {entity_id}")
        return row[0]

    return db.Statement(
        "insert into operator_actions (entity_id, lot_id, action, by, note) "
        "select entity_id, lot_id, %s, %s, %s from lot_status where entity_id = %s returning lot_id",
        (action[:100], by[:200], note, entity_id),
        into=into,
    )


def attached_entities(cur: Any) -> list[int]:
    """Entities at work whose script attached (had one when the Lot Server was last up)."""
    rows = cur.execute(
        "select s.entity_id from lot_status s join lot_entities e using (entity_id) "
        "where s.script_pid is not null and e.destroyed_at is null and s.state <> all(%s)",
        ([str(s) for s in FINISHED],),
    ).fetchall()
    return [r[0] for r in rows]


def fail_unless_finished(cur: Any, entity_id: int, reason: str) -> bool:
    """A dead script's entity fails, if it is still at work; whether it did."""
    row = cur.execute(
        "select s.state from lot_status s join lot_entities e using (entity_id) "
        "where s.entity_id = %s and e.destroyed_at is null for update of s",
        (entity_id,),
    ).fetchone()
    if row is None or LotState(row[0]) in FINISHED:
        return False
    cur.execute(
        "update lot_status set state = 'failed', reason = %s, updated_at = now() where entity_id = %s",
        (reason, entity_id),
    )
    return True


def why_not_moved(entity_id: int, waiting: frozenset[LotState]) -> db.Statement:
    """After a decision's move() found the entity in none of `waiting`: Refused UNKNOWN (no such entity)
    or NOTNOW (its state, and its lot_id), read as a snapshot of its own."""

    def into(row: tuple[int, str] | None) -> None:
        if row is None:
            raise Refused(AckCode.UNKNOWN, f"no entity {entity_id}")
        need = " or ".join(sorted(waiting))
        raise Refused(AckCode.NOTNOW, f"entity {entity_id} is {row[1]}, not {need}", lot_id=row[0])

    return db.Statement(
        "select s.lot_id, s.state from lot_status s join lot_entities e using (entity_id) "
        "where s.entity_id = %s and e.destroyed_at is null",
        (entity_id,),
        into=into,
    )


def _entity_row(cur: Any, entity_id: int) -> tuple[int, str] | None:
    return cur.execute(
        "select s.lot_id, s.state from lot_status s join lot_entities e using (entity_id) "
        "where s.entity_id = %s and e.destroyed_at is null for update of s",
        (entity_id,),
    ).fetchone()


def divide_merge(
    cur: Any, action: str, entity_id: int, other: int | None, quantity: int, asker: int | None
) -> tuple[list[int], str | None]:
    """DIV_MERGE: divide splits `quantity` new entities off one (same lot and state, parent set); merge
    folds `other` into `entity_id` (the other is destroyed). Only created or imported entities; a lot
    script (`asker`) merges only its own children. The entities it leaves, and a note."""
    me = _entity_row(cur, entity_id)
    them = _entity_row(cur, other) if action == "merge" and other is not None else None
    if me is None or (action == "merge" and them is None):
        raise Refused(AckCode.UNKNOWN, f"no entity {entity_id if me is None else other}")
    if action == "merge" and asker is not None:
        child = "select 1 from lot_entities where entity_id = %s and parent_entity_id = %s"
        if not cur.execute(child, (other, asker)).fetchone():
            raise Refused(AckCode.NOT_AUTH, f"entity {other} is not a child of lot:{asker}")
    for eid, (_lot, state) in ((entity_id, me), (other, them or me)):
        if state not in (LotState.CREATED, LotState.IMPORTED):
            raise Refused(AckCode.NOTNOW, f"entity {eid} is {state}: only created or imported ones")
    if action == "merge":
        assert them is not None
        if them != me:
            raise Refused(AckCode.NOTNOW, "only entities of one lot and one state merge")
        cur.execute("update lot_entities set destroyed_at = now() where entity_id = %s", (other,))
        return [entity_id], f"entity {other} merged into {entity_id}"
    ids = [entity_id]
    for _ in range(quantity):
        eid = db.get_new_max_value(cur, "ENTITY_ID")
        cur.execute(
            "insert into lot_entities (entity_id, lot_id, parent_entity_id) values (%s, %s, %s)",
            (eid, me[0], entity_id),
        )
        cur.execute("insert into lot_status (entity_id, lot_id, state) values (%s, %s, %s)", (eid, me[0], me[1]))
        ids.append(eid)
    return ids, None
