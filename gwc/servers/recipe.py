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

import logging
import os
import re
from pathlib import Path

from gwc.config import Config
from gwc.errors import Refused
from gwc.ipc.bus import Conversation
from gwc.ipc.codes import AckCode
from gwc.ipc.names import Conv, Msg
from gwc.module import Handler, Module
from gwc.servers import recipe_store
from gwc.servers.common import NOT_LOTS, Server
from gwc.servers.recipe_store import MAX_RECIPE, sha256

__all__ = ["MAX_RECIPE", "RECIPE_ID", "RecipeServer", "library_dir", "sha256", "version_path"]

RECIPE_ID = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}$")


def library_dir(cfg: Config) -> Path:
    """Where the ERS keeps the file of every recipe version."""
    return cfg.var / "recipe_library"


def version_path(cfg: Config, recipe_id: str, version: int) -> Path:
    return library_dir(cfg) / recipe_id / f"v{version}"


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

        written = 0
        for recipe_id, version, content in self.transaction(recipe_store.all_versions):
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
        got = self.transaction(recipe_store.approved(req.recipe_id, req.machine_id))
        data = self._file(got.recipe_id, got.version, got.content)
        if len(data) > MAX_RECIPE:
            raise Refused(
                AckCode.REC_INVAL, f"recipe {got.recipe_id} v{got.version} is {len(data)} bytes, over {MAX_RECIPE}"
            )
        try:
            text = data.decode()
        except UnicodeDecodeError:
            raise Refused(
                AckCode.REC_INVAL, f"recipe {got.recipe_id} v{got.version} library file is not UTF-8 text"
            ) from None
        if sha256(data) != got.checksum:
            self.log.warning(
                "recipe %s v%d: library file differs from what was approved; sent as it is, the machine will refuse it",
                got.recipe_id,
                got.version,
            )
        self.log.info("recipe %s v%d to %s", got.recipe_id, got.version, req.machine_id or conv.peer)
        await self.answer(
            conv, Msg.RECIPE_REPLY, recipe_id=got.recipe_id, version=got.version, checksum=got.checksum, content=text
        )

    async def store(self, conv: Conversation) -> None:
        """RECIPE_PUT: new content becomes a new, unapproved version (content equal to the latest: that one)."""
        req = self.request(conv)
        if not RECIPE_ID.match(req.recipe_id):
            raise Refused(AckCode.BAD_MESSAGE, f"recipe id {req.recipe_id!r}: letters, digits, _ . - only (64 at most)")
        content = req.content.encode()
        if len(content) > MAX_RECIPE:
            raise Refused(AckCode.BAD_MESSAGE, f"recipe is {len(content)} bytes, over the limit of {MAX_RECIPE}")
        lot = conv.initiator.startswith("lot:")
        by = conv.initiator if lot else req.by
        if lot:  # a lot script proposes (Listing 1, 6.1's recipe tweak): only for a machine it holds
            self.transaction(recipe_store.lot_may_propose(conv.initiator, req.recipe_id))
        put = recipe_store.put_version
        stored = self.transaction(lambda cur: put(cur, req.recipe_id, content, by, req.description, not lot))
        if stored.new:
            _write(version_path(self.cfg, req.recipe_id, stored.version), content)
            proposed = ", proposed by a lot: unapproved until the operator approves it" if lot else ""
            self.log.info("recipe %s v%d stored (from %s)%s", req.recipe_id, stored.version, by or conv.peer, proposed)
            if lot:
                await self.event(f"recipe {req.recipe_id} v{stored.version} proposed by {by}: `gwc recipe approve`")
        note = None if stored.new else f"same as v{stored.version}: nothing new stored"
        await self.answer(conv, Msg.RECIPE_STORE_ACK, note=note, version=stored.version, checksum=stored.checksum)

    async def approve(self, conv: Conversation) -> None:
        """RECIPE_APPR: approve a version; an edited library file is stored as a new version, approved."""
        req = self.request(conv)
        if not RECIPE_ID.match(req.recipe_id):
            raise Refused(AckCode.UNKNOWN, f"no recipe {req.recipe_id!r}")

        def on_disk(version: int) -> bytes | None:
            return _read(version_path(self.cfg, req.recipe_id, version))

        done = self.transaction(lambda cur: recipe_store.approve(cur, req.recipe_id, req.version, req.by, on_disk))
        if done.new_file is not None:
            _write(version_path(self.cfg, req.recipe_id, done.version), done.new_file)
        if done.restore is not None:
            _write(version_path(self.cfg, req.recipe_id, done.restore[0]), done.restore[1])
        by, note = req.by or conv.peer, f" ({done.note})" if done.note else ""
        self.log.info("recipe %s v%d approved by %s%s", req.recipe_id, done.version, by, note)
        await self.answer(conv, Msg.RECIPE_STORE_ACK, note=done.note, version=done.version, checksum=done.checksum)
        await self.event(f"recipe {req.recipe_id} v{done.version} approved by {by}")
