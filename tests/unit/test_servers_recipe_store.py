"""The Equipment Recipe Server's store (gwc/servers/recipe_store.py) on the template database,
without a bus: versions stored once, approval of one at a time, an edited file stored as a new
version, and the refusals (Refused) of what the tables do not hold."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any, TypeVar

import psycopg
import pytest

from gwc import db
from gwc.config import Config
from gwc.errors import Refused
from gwc.ipc.codes import AckCode
from gwc.servers import recipe_store
from gwc.servers.recipe_store import sha256

T = TypeVar("T")


@pytest.fixture
def ers(cell_config: Config) -> Iterator[psycopg.Connection[Any]]:
    """The ERS's own connection (role gwc_ers)."""
    with db.connect(cell_config, role="ers") as c:
        yield c


def step(conn: psycopg.Connection[Any], fn: Callable[[Any], T]) -> T:
    return db.transaction(conn, fn)


def approved_versions(conn: psycopg.Connection[Any], recipe_id: str) -> list[int]:
    rows = conn.execute("select version from recipe_versions where recipe_id = %s and approved", (recipe_id,))
    return [v for (v,) in rows.fetchall()]


def test_the_approved_version_is_read_for_a_machine_it_is_for_only(ers: psycopg.Connection[Any]) -> None:
    got = step(ers, recipe_store.approved("mill_pawn", "wc1"))
    assert got.version == 1 and got.checksum == sha256(got.content) and got.content.startswith(b"# mill_pawn v1")
    for recipe_id, machine, why in (
        ("mill_pawn", "cmm_wc", "not for machine cmm_wc"),
        ("nope", None, "no recipe 'nope'"),
    ):
        with pytest.raises(Refused) as refused:
            step(ers, recipe_store.approved(recipe_id, machine))
        assert refused.value.ack_code == AckCode.REC_INVAL and why in refused.value.detail


def test_new_content_is_a_new_unapproved_version_and_the_same_content_is_not(ers: psycopg.Connection[Any]) -> None:
    put = recipe_store.put_version
    first = step(ers, lambda cur: put(cur, "mill_pawn", b"# v2\n", "op", "a better pawn", True))
    assert (first.version, first.new, first.checksum) == (2, True, sha256(b"# v2\n"))
    again = step(ers, lambda cur: put(cur, "mill_pawn", b"# v2\n", "op", None, True))
    assert (again.version, again.new) == (2, False)
    assert approved_versions(ers, "mill_pawn") == [1]
    fresh = step(ers, lambda cur: put(cur, "brand_new", b"RUN\n", "op", "new", True))
    assert (fresh.version, fresh.new) == (1, True)


def test_approval_moves_to_one_version_and_an_edited_file_becomes_a_version_of_its_own(
    ers: psycopg.Connection[Any],
) -> None:
    step(ers, lambda cur: recipe_store.put_version(cur, "mill_pawn", b"# v2\n", "op", None, True))
    done = step(ers, lambda cur: recipe_store.approve(cur, "mill_pawn", 2, "op", lambda v: b"# v2\n"))
    assert (done.version, done.note, done.restore, done.new_file) == (2, None, None, None)
    assert approved_versions(ers, "mill_pawn") == [2]
    edited = step(ers, lambda cur: recipe_store.approve(cur, "mill_pawn", 1, "op", lambda v: b"# edited\n"))
    assert edited.version == 3 and edited.new_file == b"# edited\n" and edited.restore is not None
    assert edited.restore[0] == 1 and edited.checksum == sha256(b"# edited\n")
    assert approved_versions(ers, "mill_pawn") == [3]
    with pytest.raises(Refused) as refused:
        step(ers, lambda cur: recipe_store.approve(cur, "mill_pawn", 9, "op", lambda v: None))
    assert refused.value.ack_code == AckCode.UNKNOWN and "no version 9" in refused.value.detail
    assert approved_versions(ers, "mill_pawn") == [3]  # the refusal rolled the step back


def test_a_lot_proposes_versions_only_of_recipes_for_machines_reserved_to_it(ers: psycopg.Connection[Any]) -> None:
    for recipe_id, why in (("mill_pawn", "no machine reserved to lot:5"), ("nope", "no recipe 'nope'")):
        with pytest.raises(Refused) as refused:
            step(ers, recipe_store.lot_may_propose("lot:5", recipe_id))
        assert refused.value.ack_code == AckCode.NOT_AUTH and why in refused.value.detail
