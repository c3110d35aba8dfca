"""The Equipment Recipe Server's database side: every read and write of RECIPES, RECIPE_VERSIONS and
OP_MACHINE_RECIPE its handlers make (gwc/servers/recipe.py parses, keeps the library files, answers).

A function either takes the cursor of one transaction or returns a one-statement `Statement` (run
alone, without BEGIN and COMMIT: a RECIPE_GET comes with every run set up). Each returns a dataclass
and raises `Refused` with the ack code and the reason when the request does not fit the tables.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from gwc.db import Statement
from gwc.errors import Refused
from gwc.ipc.codes import AckCode

MAX_RECIPE = 48_000  # bytes: a recipe travels in one bus datagram (wire.MAX_DATAGRAM, with headroom)


def sha256(content: bytes) -> str:
    return hashlib.sha256(content).hexdigest()


@dataclass(frozen=True)
class Approved:
    """A recipe's approved version, as recorded: what RECIPE_GET sends (the file beside it may differ)."""

    recipe_id: str
    version: int
    checksum: str
    content: bytes


@dataclass(frozen=True)
class Stored:
    """RECIPE_PUT's outcome: the version that holds the content; `new` False if the latest already did."""

    version: int
    checksum: str
    new: bool


@dataclass(frozen=True)
class Approval:
    """RECIPE_APPR's outcome: the version now approved, and the library files to write after the commit:
    an edited file stored as a new version (`new_file`), the old version's file put back (`restore`)."""

    version: int
    checksum: str
    note: str | None
    restore: tuple[int, bytes] | None
    new_file: bytes | None


def all_versions(cur: Any) -> list[tuple[str, int, bytes]]:
    """(recipe_id, version, content) of every version kept: what the library's files hold."""
    rows = cur.execute("select recipe_id, version, content from recipe_versions").fetchall()
    return [(r, v, bytes(c)) for r, v, c in rows]


def approved(recipe_id: str, machine_id: str | None) -> Statement:
    """The approved version of a recipe for a machine (any machine when None); Refused REC_INVAL when
    the recipe is unknown, has no approved version, or is not for that machine."""

    def into(row: tuple[Any, ...]) -> Approved:
        known, version, checksum, content, bound = row
        if not known:
            raise Refused(AckCode.REC_INVAL, f"no recipe {recipe_id!r}")
        if version is None:
            raise Refused(AckCode.REC_INVAL, f"recipe {recipe_id} has no approved version")
        if not bound:
            raise Refused(AckCode.REC_INVAL, f"recipe {recipe_id} is not for machine {machine_id}")
        return Approved(recipe_id, version, checksum, bytes(content))

    return Statement(
        "select exists (select 1 from recipes where recipe_id = %(r)s), v.version, v.checksum, v.content, "
        "%(m)s::text is null or exists (select 1 from op_machine_recipe where recipe_id = %(r)s "
        "and machine_id = %(m)s) "
        "from (select) one left join recipe_versions v on v.recipe_id = %(r)s and v.approved",
        {"r": recipe_id, "m": machine_id},
        into=into,
    )


def lot_may_propose(asker: str, recipe_id: str) -> Statement:
    """Refused NOT_AUTH unless lot script `asker` (lot:E) may propose a version of this recipe: it may
    for a recipe that exists and is for a machine RESERVED_MACHINES gives to E."""
    entity = asker[4:]

    def into(row: tuple[str | None]) -> None:
        if row[0] is not None:
            raise Refused(AckCode.NOT_AUTH, row[0])

    return Statement(
        "select case when not exists (select 1 from recipes where recipe_id = %(r)s) then %(unknown)s "
        "when not exists (select 1 from op_machine_recipe o join reserved_machines m using (machine_id) "
        "where o.recipe_id = %(r)s and m.entity_id = %(e)s) then %(unheld)s end",
        {
            "r": recipe_id,
            "e": int(entity) if entity.isdigit() else -1,
            "unknown": f"no recipe {recipe_id!r}: a lot script proposes versions of known recipes only",
            "unheld": f"recipe {recipe_id} is for no machine reserved to {asker}",
        },
        "one",
        into=into,
    )


def put_version(
    cur: Any, recipe_id: str, content: bytes, by: str | None, description: str | None, describe: bool
) -> Stored:
    """New content becomes a new, unapproved version (content equal to the latest: that one). The
    recipe is made if new; its description set when `describe` (not by a lot's proposal)."""
    checksum = sha256(content)
    cur.execute(
        "insert into recipes (recipe_id, description) values (%s, %s) on conflict do nothing", (recipe_id, description)
    )
    cur.execute("select 1 from recipes where recipe_id = %s for update", (recipe_id,))
    if description and describe:
        cur.execute("update recipes set description = %s where recipe_id = %s", (description, recipe_id))
    last = cur.execute(
        "select version, checksum from recipe_versions where recipe_id = %s order by version desc limit 1",
        (recipe_id,),
    ).fetchone()
    if last is not None and last[1] == checksum:
        return Stored(last[0], checksum, False)
    version = (last[0] if last else 0) + 1
    cur.execute(
        "insert into recipe_versions (recipe_id, version, content, checksum, created_by) values (%s, %s, %s, %s, %s)",
        (recipe_id, version, content, checksum, by),
    )
    return Stored(version, checksum, True)


def approve(
    cur: Any, recipe_id: str, version: int | None, by: str | None, on_disk: Callable[[int], bytes | None]
) -> Approval:
    """Approve a version (the latest when None), and no other. If its library file (`on_disk`) was
    edited, the edit is stored as a new version and that one is approved; the old file is restored."""
    cur.execute("select 1 from recipes where recipe_id = %s for update", (recipe_id,))
    rows = cur.execute(
        "select version, checksum, content, approved from recipe_versions where recipe_id = %s order by version",
        (recipe_id,),
    ).fetchall()
    if not rows:
        raise Refused(AckCode.UNKNOWN, f"no recipe {recipe_id!r} (or it has no versions)")
    chosen = rows[-1] if version is None else next((r for r in rows if r[0] == version), None)
    if chosen is None:
        raise Refused(AckCode.UNKNOWN, f"recipe {recipe_id} has no version {version}")
    version, checksum, content, was_approved = chosen[0], chosen[1], bytes(chosen[2]), chosen[3]
    file = on_disk(version)
    restore, note, new_file = None, None, None
    if file is not None and sha256(file) != checksum:
        if len(file) > MAX_RECIPE:
            raise Refused(AckCode.UNKNOWN, f"the edited file of v{version} is {len(file)} bytes, over {MAX_RECIPE}")
        restore, old = (version, content), version
        version, checksum, new_file = rows[-1][0] + 1, sha256(file), file
        note = f"library file of v{old} was edited: stored as v{version}, approved; v{old} restored"
        cur.execute(
            "insert into recipe_versions (recipe_id, version, content, checksum, created_by, note) "
            "values (%s, %s, %s, %s, %s, %s)",
            (recipe_id, version, file, checksum, by, f"edit of v{old}"),
        )
    else:
        if file is None:
            restore = (version, content)
        if was_approved:
            note = f"v{version} was already approved"
    cur.execute(
        "update recipe_versions set approved = false where recipe_id = %s and approved and version <> %s",
        (recipe_id, version),
    )
    cur.execute(
        "update recipe_versions set approved = true where recipe_id = %s and version = %s", (recipe_id, version)
    )
    return Approval(version, checksum, note, restore, new_file)
