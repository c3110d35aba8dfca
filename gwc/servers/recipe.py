"""The Equipment Recipe Server (thesis 1.4.1): the librarian of recipes, the one writer of RECIPES,
RECIPE_VERSIONS and OP_MACHINE_RECIPE.

Every version of a recipe is kept: its content (never modified once stored) and the sha256 of that
content go into RECIPE_VERSIONS, and the ERS keeps a copy of each version as a file in the recipe
library, var/recipe_library/<recipe_id>/v<version>: that file is the recipe "on disk", the one a
person might open and edit. At most one version of a recipe is approved.

RECIPE_GET sends a machine the approved version: the checksum recorded for it, and the content of
its library file as it is now. The WC checks one against the other before the machine runs it, so
a file edited after approval is refused (Rec_Inval and alarm REC_INVAL, gwc/wc/wc.py); nothing runs
that was not approved. RECIPE_PUT stores new content (an upload from a machine, `gwc recipe add`)
as a new, unapproved version. RECIPE_APPR (`gwc recipe approve`) approves one; if its library file
was edited, the edit is the operator's choice now: it is stored as a new version and that one is
approved, and the old version's file is put back as it was, so the original stays unmodified.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
from pathlib import Path
from typing import Any

from gwc.config import Config
from gwc.db import Statement
from gwc.ipc.bus import Conversation
from gwc.ipc.codes import AckCode
from gwc.ipc.names import Conv, Msg
from gwc.module import Handler, Module
from gwc.servers.common import NOT_LOTS, Server

RECIPE_ID = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}$")
MAX_RECIPE = 48_000  # bytes: a recipe travels in one bus datagram (wire.MAX_DATAGRAM, with headroom)


def library_dir(cfg: Config) -> Path:
    """Where the ERS keeps the file of every recipe version."""
    return cfg.var / "recipe_library"


def version_path(cfg: Config, recipe_id: str, version: int) -> Path:
    return library_dir(cfg) / recipe_id / f"v{version}"


def sha256(content: bytes) -> str:
    return hashlib.sha256(content).hexdigest()


def _write(path: Path, content: bytes) -> None:
    """Write a library file whole or not at all."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_bytes(content)
    tmp.replace(path)


def _read(path: Path) -> bytes | None:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        return None


def lot_may_propose(asker: str, recipe_id: str) -> Statement:
    """Why lot script `asker` (lot:E) may not propose a version of this recipe, or None: it may for a
    recipe that exists and is for a machine RESERVED_MACHINES gives to E (one statement, run alone)."""
    entity = asker[4:]
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
    )


class RecipeServer(Server, Module):
    role = "ers"
    ignored_peers = NOT_LOTS

    def __init__(self, cfg: Config, name: str, log: logging.Logger) -> None:
        super().__init__(cfg, name, log)
        self.library = library_dir(cfg)

    def handlers(self) -> dict[str, Handler]:
        return {Conv.RECIPE_GET: self.fetch, Conv.RECIPE_PUT: self.store, Conv.RECIPE_APPR: self.approve}

    async def on_startup(self) -> str:
        """Give every version its library file if it has none (first start, a new var/)."""

        def versions(cur: Any) -> list[tuple[str, int, bytes]]:
            return cur.execute("select recipe_id, version, content from recipe_versions").fetchall()

        written = 0
        for recipe_id, version, content in self.transaction(versions):
            path = version_path(self.cfg, recipe_id, version)
            if not path.exists():
                _write(path, bytes(content))
                written += 1
        self.log.info("recipe library %s: %d file(s) written", self.library, written)
        return AckCode.ACK_OK

    def _file(self, recipe_id: str, version: int, content: bytes) -> bytes:
        """A version's library file as it is now; a missing one is put back from the database first."""
        path = version_path(self.cfg, recipe_id, version)
        data = _read(path)
        if data is None:
            self.log.warning("library file %s was missing: restored from the database", path)
            _write(path, content)
            data = content
        return data

    async def fetch(self, conv: Conversation) -> None:
        """RECIPE_GET: the approved version for a machine; Rec_Inval when there is none to give."""
        req = self.request(conv)
        ack = Msg.RECIPE_REPLY

        # One statement, run alone: is the recipe known, its approved version, is it for this machine.
        read = Statement(
            "select exists (select 1 from recipes where recipe_id = %(r)s), v.version, v.checksum, v.content, "
            "%(m)s::text is null or exists (select 1 from op_machine_recipe where recipe_id = %(r)s "
            "and machine_id = %(m)s) "
            "from (select) one left join recipe_versions v on v.recipe_id = %(r)s and v.approved",
            {"r": req.recipe_id, "m": req.machine_id},
        )
        known, version, checksum, original, bound = self.transaction(read)
        if not known:
            return await self.answer(conv, ack, AckCode.REC_INVAL, f"no recipe {req.recipe_id!r}")
        if version is None:
            return await self.answer(conv, ack, AckCode.REC_INVAL, f"recipe {req.recipe_id} has no approved version")
        if not bound:
            return await self.answer(
                conv, ack, AckCode.REC_INVAL, f"recipe {req.recipe_id} is not for machine {req.machine_id}"
            )
        data = self._file(req.recipe_id, version, bytes(original))
        if len(data) > MAX_RECIPE:
            return await self.answer(
                conv,
                ack,
                AckCode.REC_INVAL,
                f"recipe {req.recipe_id} v{version} is {len(data)} bytes, over {MAX_RECIPE}",
            )
        try:
            text = data.decode()
        except UnicodeDecodeError:
            return await self.answer(
                conv, ack, AckCode.REC_INVAL, f"recipe {req.recipe_id} v{version} library file is not UTF-8 text"
            )
        if sha256(data) != checksum:
            self.log.warning(
                "recipe %s v%d: library file differs from what was approved; sent as it is, the machine will refuse it",
                req.recipe_id,
                version,
            )
        self.log.info("recipe %s v%d to %s", req.recipe_id, version, req.machine_id or conv.peer)
        await self.answer(
            conv, ack, AckCode.ACK_OK, recipe_id=req.recipe_id, version=version, checksum=checksum, content=text
        )

    async def store(self, conv: Conversation) -> None:
        """RECIPE_PUT: new content becomes a new, unapproved version (content equal to the latest: that one)."""
        req = self.request(conv)
        ack = Msg.RECIPE_STORE_ACK
        if not RECIPE_ID.match(req.recipe_id):
            return await self.answer(
                conv, ack, AckCode.BAD_MESSAGE, f"recipe id {req.recipe_id!r}: letters, digits, _ . - only (64 at most)"
            )
        content = req.content.encode()
        if len(content) > MAX_RECIPE:
            return await self.answer(
                conv, ack, AckCode.BAD_MESSAGE, f"recipe is {len(content)} bytes, over the limit of {MAX_RECIPE}"
            )
        checksum = sha256(content)
        by = req.by
        lot = conv.initiator.startswith("lot:")
        if lot:  # a lot script proposes (Listing 1, 6.1's recipe tweak): only for a machine it holds
            by = conv.initiator
            refusal = self.transaction(lot_may_propose(conv.initiator, req.recipe_id))[0]
            if refusal is not None:
                return await self.answer(conv, ack, AckCode.NOT_AUTH, refusal)

        def put(cur: Any) -> tuple[int, bool]:
            cur.execute(
                "insert into recipes (recipe_id, description) values (%s, %s) on conflict do nothing",
                (req.recipe_id, req.description),
            )
            cur.execute("select 1 from recipes where recipe_id = %s for update", (req.recipe_id,))
            if req.description and not lot:
                cur.execute(
                    "update recipes set description = %s where recipe_id = %s", (req.description, req.recipe_id)
                )
            last = cur.execute(
                "select version, checksum from recipe_versions where recipe_id = %s order by version desc limit 1",
                (req.recipe_id,),
            ).fetchone()
            if last is not None and last[1] == checksum:
                return last[0], False
            version = (last[0] if last else 0) + 1
            cur.execute(
                "insert into recipe_versions (recipe_id, version, content, checksum, created_by) "
                "values (%s, %s, %s, %s, %s)",
                (req.recipe_id, version, content, checksum, by),
            )
            return version, True

        version, new = self.transaction(put)
        if new:
            _write(version_path(self.cfg, req.recipe_id, version), content)
            self.log.info(
                "recipe %s v%d stored (from %s)%s",
                req.recipe_id,
                version,
                by or conv.peer,
                ", proposed by a lot: unapproved until the operator approves it" if lot else "",
            )
            if lot:
                await self.event(f"recipe {req.recipe_id} v{version} proposed by {by}: `gwc recipe approve`")
        await self.answer(
            conv,
            ack,
            AckCode.ACK_OK,
            None if new else f"same as v{version}: nothing new stored",
            version=version,
            checksum=checksum,
        )

    async def approve(self, conv: Conversation) -> None:
        """RECIPE_APPR: approve a version; an edited library file is stored as a new version, approved."""
        req = self.request(conv)
        ack = Msg.RECIPE_STORE_ACK
        if not RECIPE_ID.match(req.recipe_id):
            return await self.answer(conv, ack, AckCode.UNKNOWN, f"no recipe {req.recipe_id!r}")

        def appr(cur: Any) -> tuple[int, str, str | None, tuple[int, bytes] | None, bytes | None] | str:
            cur.execute("select 1 from recipes where recipe_id = %s for update", (req.recipe_id,))
            rows = cur.execute(
                "select version, checksum, content, approved from recipe_versions "
                "where recipe_id = %s order by version",
                (req.recipe_id,),
            ).fetchall()
            if not rows:
                return f"no recipe {req.recipe_id!r} (or it has no versions)"
            chosen = rows[-1] if req.version is None else next((r for r in rows if r[0] == req.version), None)
            if chosen is None:
                return f"recipe {req.recipe_id} has no version {req.version}"
            version, checksum, content, approved = chosen[0], chosen[1], bytes(chosen[2]), chosen[3]
            on_disk = _read(version_path(self.cfg, req.recipe_id, version))
            restore, note, new_file = None, None, None
            if on_disk is not None and sha256(on_disk) != checksum:
                if len(on_disk) > MAX_RECIPE:
                    return f"the edited file of v{version} is {len(on_disk)} bytes, over {MAX_RECIPE}"
                restore = (version, content)
                new = rows[-1][0] + 1
                note = f"library file of v{version} was edited: stored as v{new}, approved; v{version} restored"
                cur.execute(
                    "insert into recipe_versions (recipe_id, version, content, checksum, created_by, note) "
                    "values (%s, %s, %s, %s, %s, %s)",
                    (req.recipe_id, new, on_disk, sha256(on_disk), req.by, f"edit of v{version}"),
                )
                version, checksum, new_file, approved = new, sha256(on_disk), on_disk, False
            else:
                if on_disk is None:
                    restore = (version, content)
                if approved:
                    note = f"v{version} was already approved"
            cur.execute(
                "update recipe_versions set approved = false where recipe_id = %s and approved and version <> %s",
                (req.recipe_id, version),
            )
            cur.execute(
                "update recipe_versions set approved = true where recipe_id = %s and version = %s",
                (req.recipe_id, version),
            )
            return version, checksum, note, restore, new_file

        result = self.transaction(appr)
        if isinstance(result, str):
            return await self.answer(conv, ack, AckCode.UNKNOWN, result)
        version, checksum, note, restore, new_file = result
        if new_file is not None:
            _write(version_path(self.cfg, req.recipe_id, version), new_file)
        if restore is not None:
            _write(version_path(self.cfg, req.recipe_id, restore[0]), restore[1])
        self.log.info(
            "recipe %s v%d approved by %s%s", req.recipe_id, version, req.by or conv.peer, f" ({note})" if note else ""
        )
        await self.answer(conv, ack, AckCode.ACK_OK, note, version=version, checksum=checksum)
        await self.event(f"recipe {req.recipe_id} v{version} approved by {req.by or conv.peer}")
