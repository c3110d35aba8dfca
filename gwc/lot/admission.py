"""Lot scripts that scale with the work in progress, not with the order book (docs/lot-scripts.md,
*Admission*).

An entity of an order costs a row until its script can work: a host's agent runs at most
`gwc.budget.Budget.running` lot scripts at once and keeps the rest in a `LotQueue`, first come first
started, starting the next as one ends. The queue is a folder of empty marker files
(`var/run/lot-E.queued`), so an agent that dies and starts again finds it as it left it, as it finds the
scripts it ran by their pid files.
"""

from __future__ import annotations

import contextlib
import errno
import os
from pathlib import Path


class LotQueue:
    """Entities whose scripts wait for a place, oldest first: `var/run/lot-E.queued` marker files."""

    def __init__(self, run_dir: Path) -> None:
        self.run_dir = run_dir

    def marker(self, entity_id: int) -> Path:
        return self.run_dir / f"lot-{entity_id}.queued"

    def add(self, entity_id: int) -> bool:
        """Queue the entity's script; False if it is queued already. The marker is created exclusively and
        never through a link another user planted."""
        self.run_dir.mkdir(parents=True, exist_ok=True)
        try:
            fd = os.open(self.marker(entity_id), os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
        except FileExistsError:
            return False
        os.close(fd)
        return True

    def remove(self, entity_id: int) -> None:
        with contextlib.suppress(FileNotFoundError):
            self.marker(entity_id).unlink()

    def __contains__(self, entity_id: object) -> bool:
        return isinstance(entity_id, int) and self.marker(entity_id).is_file()

    def pending(self) -> list[int]:
        """The queued entities in the order they came: by entity id, which the Lot Server hands out in
        order (an order's entities, then the next order's)."""
        try:
            names = os.listdir(self.run_dir)
        except OSError as e:
            if e.errno == errno.ENOENT:
                return []
            raise
        found = []
        for name in names:
            stem, dot, ext = name.partition(".")
            kind, _, entity = stem.partition("-")
            if dot and ext == "queued" and kind == "lot" and entity.isdigit():
                found.append(int(entity))
        return sorted(found)
