"""The recipe library (Equipment Recipe Server, 1.4.1): storing and approving versions is asked of the
ERS (RECIPE_PUT, RECIPE_APPR), the only writer of recipes; the versions and the library files are read."""

from __future__ import annotations

from typing import Any

from gwc import db
from gwc.client.session import ANSWER, ask, operator
from gwc.config import Config
from gwc.errors import Refused
from gwc.ipc import BlockingBus
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode
from gwc.ipc.names import Conv, Msg
from gwc.servers.recipe import sha256, version_path

__all__ = ["approve_recipe", "file_state", "list_recipes", "recipe_versions", "store_recipe"]


def _ask_ers(bus: BlockingBus, cls: str, msg: Message) -> Message:
    ack = ask(bus, cls, msg, "ers", ANSWER)
    if ack.ack_code != AckCode.ACK_OK:
        raise Refused(ack.ack_code, ack.note or "")
    return ack


def store_recipe(bus: BlockingBus, recipe_id: str, content: str, description: str | None = None) -> Message:
    """RECIPE_PUT: `content` as a new version of the recipe (a new recipe if unknown). The ERS's answer:
    version, checksum, note; Refused if it says no."""
    return _ask_ers(
        bus,
        Conv.RECIPE_PUT,
        message(Msg.RECIPE_STORE, recipe_id=recipe_id, content=content, by=operator(), description=description),
    )


def approve_recipe(bus: BlockingBus, recipe_id: str, version: int | None = None) -> Message:
    """RECIPE_APPR: approve a version (default the latest; an edited library file is stored as a new
    version first). The ERS's answer: version, checksum, note; Refused if it says no."""
    return _ask_ers(
        bus, Conv.RECIPE_APPR, message(Msg.RECIPE_APPROVE, recipe_id=recipe_id, version=version, by=operator())
    )


def file_state(cfg: Config, recipe_id: str, version: int, checksum: str) -> str:
    """ok, MODIFIED or missing: the library file of a version against its recorded checksum."""
    try:
        data = version_path(cfg, recipe_id, version).read_bytes()
    except FileNotFoundError:
        return "missing"
    return "ok" if sha256(data) == checksum else "MODIFIED"


def _rows(cfg: Config, sql: str, *params: Any) -> list[dict[str, Any]]:
    with db.connect(cfg, role="hi") as conn:
        cur = conn.execute(sql, params)
        names = [d.name for d in cur.description or []]
        return [dict(zip(names, r)) for r in cur.fetchall()]


def list_recipes(cfg: Config) -> list[dict[str, Any]]:
    """Every recipe: its versions, the approved one and whether its library file is intact, its machines."""
    rows = _rows(
        cfg,
        """
        select r.recipe_id, r.description, count(v.version) as versions, a.version as approved, a.checksum,
               (select string_agg(distinct m.machine_id, ' ' order by m.machine_id) from op_machine_recipe m
                 where m.recipe_id = r.recipe_id) as machines
        from recipes r left join recipe_versions v using (recipe_id)
        left join recipe_versions a on a.recipe_id = r.recipe_id and a.approved
        group by r.recipe_id, r.description, a.version, a.checksum order by r.recipe_id""",
    )
    for r in rows:
        r["file"] = file_state(cfg, r["recipe_id"], r["approved"], r["checksum"]) if r["approved"] else None
        r["checksum"] = r["checksum"][:12] if r["checksum"] else None
    return rows


def recipe_versions(cfg: Config, recipe_id: str) -> list[dict[str, Any]]:
    """The versions of a recipe, oldest first, each with its content and the state of its library file."""
    rows = _rows(
        cfg,
        "select version, approved, checksum, created_by, created_at, note, content "
        "from recipe_versions where recipe_id = %s order by version",
        recipe_id,
    )
    for r in rows:
        r["file"] = file_state(cfg, recipe_id, r["version"], r["checksum"])
        r["created_at"] = r["created_at"].strftime("%Y-%m-%d %H:%M:%S")
    return rows
