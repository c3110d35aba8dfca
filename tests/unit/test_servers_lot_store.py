"""The Lot Server's store (gwc/servers/lot_store.py) on the template database, without a bus: what
each step writes, what it answers a repeat with, and what it refuses (Refused, the step rolled back)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any, TypeVar

import psycopg
import pytest

from gwc import db
from gwc.config import Config
from gwc.errors import Refused
from gwc.ipc.codes import AckCode, LotState
from gwc.servers import lot_store
from gwc.servers.lot_store import NewLot

T = TypeVar("T")
ACTIVE = frozenset(LotState) - {LotState.EXPORTED, LotState.FAILED}


@pytest.fixture
def ls(cell_config: Config) -> Iterator[psycopg.Connection[Any]]:
    """The Lot Server's own connection (role gwc_ls)."""
    with db.connect(cell_config, role="ls") as c:
        yield c


def step(conn: psycopg.Connection[Any], fn: Callable[[Any], T]) -> T:
    return db.transaction(conn, fn)


def states(conn: psycopg.Connection[Any], ids: list[int]) -> list[str]:
    rows = conn.execute("select state from lot_status where entity_id = any(%s) order by entity_id", (ids,))
    return [r[0] for r in rows.fetchall()]


def test_create_lot_makes_one_created_entity_per_unit_and_a_repeat_gets_the_same(ls: psycopg.Connection[Any]) -> None:
    new = NewLot("alum_chess_set", 3, request_id="order-1/1")
    made = step(ls, lambda cur: lot_store.create_lot(cur, new))
    assert made.new and len(made.entity_ids) == 3
    assert states(ls, made.entity_ids) == ["created"] * 3
    lot = ls.execute("select lot_type, script_id, quantity from lots where lot_id = %s", (made.lot_id,)).fetchone()
    assert lot == ("CMM_LOT", "chess", 3)  # the product's, as none was asked for
    again = step(ls, lambda cur: lot_store.create_lot(cur, new))
    assert (again.lot_id, again.entity_ids, again.new) == (made.lot_id, made.entity_ids, False)
    more = step(ls, lambda cur: lot_store.create_lot(cur, NewLot("alum_chess_set", 2, lot_id=made.lot_id)))
    assert more.lot_id == made.lot_id and len(more.entity_ids) == 2
    units = ls.execute("select unit from lot_entities where entity_id = any(%s) order by unit", (more.entity_ids,))
    assert [u for (u,) in units.fetchall()] == [4, 5]


@pytest.mark.parametrize(
    "new, why",
    [
        (NewLot("no_such_product", 1), "no product 'no_such_product'"),
        (NewLot("alum_chess_set", 1, script_id="nope"), "no lot script 'nope'"),
        (NewLot("alum_chess_set", 1, work_order_id=999), "no work order 999"),
        (NewLot("alum_chess_set", 1, lot_id=999), "no lot 999"),
        (NewLot("alum_chess_set", 1, parent=999), "entity 999 is unknown"),
    ],
)
def test_create_lot_refuses_what_the_tables_do_not_hold_and_writes_nothing(
    ls: psycopg.Connection[Any], new: NewLot, why: str
) -> None:
    with pytest.raises(Refused) as refused:
        step(ls, lambda cur: lot_store.create_lot(cur, new))
    assert refused.value.ack_code == AckCode.UNKNOWN and why in refused.value.detail
    assert ls.execute("select count(*) from lot_entities").fetchone() == (0,)


def test_entity_moves_in_one_statement_or_is_refused_notnow_with_its_state(ls: psycopg.Connection[Any]) -> None:
    (eid,) = step(ls, lambda cur: lot_store.create_lot(cur, NewLot("alum_chess_set", 1))).entity_ids
    came_from = frozenset({LotState.CREATED})
    assert step(ls, lot_store.move(eid, LotState.WAITING_IMPORT, came_from, None, keep=False)) is not None
    assert (
        step(ls, lot_store.move(eid, LotState.WAITING_IMPORT, came_from, None, keep=False)) is None
    )  # not created now
    with pytest.raises(Refused) as refused:
        step(
            ls,
            lambda cur: lot_store.entity_step(cur, eid, "completed", LotState.COMPLETED, frozenset({LotState.RUNNING})),
        )
    assert refused.value.ack_code == AckCode.NOTNOW
    assert refused.value.fields["state"] == "waiting_import" and refused.value.fields["lot_id"] is not None
    with pytest.raises(Refused) as refused:
        step(ls, lambda cur: lot_store.entity_step(cur, 424242, "state", None, frozenset(LotState)))
    assert refused.value.ack_code == AckCode.UNKNOWN


def test_attach_answers_the_lot_script_and_an_exported_entity_comes_back_in_a_new_lot(
    ls: psycopg.Connection[Any],
) -> None:
    made = step(ls, lambda cur: lot_store.create_lot(cur, NewLot("alum_chess_set", 1, priority=7)))
    (eid,) = made.entity_ids
    done = step(ls, lambda cur: lot_store.entity_step(cur, eid, "attach", None, ACTIVE, script_pid=4321))
    assert done.attached["script_id"] == "chess" and done.attached["priority"] == 7
    assert done.attached["script_path"] == "gwc/lot/scripts/chess.py"
    ls.execute("update lot_status set state = 'exported' where entity_id = %s", (eid,))
    ls.commit()
    back = step(
        ls,
        lambda cur: lot_store.entity_step(
            cur, eid, "import", LotState.WAITING_IMPORT, frozenset({LotState.CREATED, LotState.EXPORTED})
        ),
    )
    assert back.state == LotState.WAITING_IMPORT and back.lot_id != made.lot_id
    assert back.note == f"re-imported entity: lot {made.lot_id} -> lot {back.lot_id}"
    assert states(ls, [eid]) == ["waiting_import"]


def test_divide_merge_split_and_fold_back_only_before_work_and_only_ones_own(ls: psycopg.Connection[Any]) -> None:
    (eid,) = step(ls, lambda cur: lot_store.create_lot(cur, NewLot("alum_chess_set", 1))).entity_ids
    ids, note = step(ls, lambda cur: lot_store.divide_merge(cur, "divide", eid, None, 2, None))
    assert ids[0] == eid and len(ids) == 3 and note is None
    assert states(ls, ids) == ["created"] * 3
    with pytest.raises(Refused) as refused:  # lot:999 merges only its own children
        step(ls, lambda cur: lot_store.divide_merge(cur, "merge", eid, ids[1], 1, 999))
    assert refused.value.ack_code == AckCode.NOT_AUTH
    kept, note = step(ls, lambda cur: lot_store.divide_merge(cur, "merge", eid, ids[1], 1, eid))
    assert kept == [eid] and note == f"entity {ids[1]} merged into {eid}"
    ls.execute("update lot_status set state = 'running' where entity_id = %s", (ids[2],))
    ls.commit()
    with pytest.raises(Refused) as refused:
        step(ls, lambda cur: lot_store.divide_merge(cur, "merge", eid, ids[2], 1, None))
    assert refused.value.ack_code == AckCode.NOTNOW and "only created or imported" in refused.value.detail


def test_an_operator_action_is_kept_and_a_refused_decision_says_why(ls: psycopg.Connection[Any]) -> None:
    made = step(ls, lambda cur: lot_store.create_lot(cur, NewLot("alum_chess_set", 1)))
    (eid,) = made.entity_ids
    assert step(ls, lot_store.record_action(eid, "cancel", "op", None)) == made.lot_id
    with pytest.raises(Refused) as refused:
        step(ls, lot_store.record_action(424242, "cancel", "op", None))
    assert refused.value.ack_code == AckCode.UNKNOWN
    with pytest.raises(Refused) as refused:
        step(ls, lot_store.why_not_moved(eid, frozenset({LotState.WAITING_EXPORT})))
    assert refused.value.ack_code == AckCode.NOTNOW and refused.value.fields == {"lot_id": made.lot_id}
    assert step(ls, lambda cur: lot_store.fail_unless_finished(cur, eid, "script died")) is True
    assert states(ls, [eid]) == ["failed"]
    assert step(ls, lambda cur: lot_store.fail_unless_finished(cur, eid, "again")) is False
