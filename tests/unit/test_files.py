"""gwc.files.rewrite, through a lot's traveller (the ME's run number: tests/unit/test_me.py): every save
leaves the file whole, and after the second save no file is created or replaced: the new text goes
into the previous version's file and the two names swap."""

from __future__ import annotations

import errno
import json
from pathlib import Path

import pytest

from gwc import files
from gwc.config import Config
from gwc.lot.model import forget_previous_traveller, read_traveller, save_traveller, traveller_path
from tests.conftest import make_config


@pytest.fixture
def cfg(tmp_path: Path) -> Config:
    return make_config(tmp_path, None)


def doc(n: int, pad: int = 0) -> dict[str, object]:
    return {"entity_id": 7, "steps": [{"n": i, "note": "x" * pad} for i in range(n)]}


def test_each_save_is_whole_and_two_files_take_turns(cfg: Config) -> None:
    path = traveller_path(cfg, 7)
    prev = files.previous(path)
    inodes = set()
    for n in range(1, 8):
        # Long and short in turn: a shorter text written over a longer one must leave nothing behind.
        save_traveller(cfg, 7, doc(n, pad=400 if n % 2 else 0))
        assert read_traveller(cfg, 7) == doc(n, pad=400 if n % 2 else 0)
        if n > 1:
            assert json.loads(prev.read_text()) == doc(n - 1, pad=400 if (n - 1) % 2 else 0)
        inodes.add(path.stat().st_ino)
    assert len(inodes) == 2  # the same two files from the second save on: none created, none replaced
    assert sorted(p.name for p in path.parent.iterdir()) == [path.name, prev.name]

    forget_previous_traveller(cfg, 7)
    assert not prev.exists() and read_traveller(cfg, 7) == doc(7, pad=400)
    forget_previous_traveller(cfg, 7)  # twice: nothing to do


def test_a_torn_previous_version_does_not_reach_the_traveller(cfg: Config) -> None:
    """What a kill -9 mid-write leaves (a half-written previous version) is overwritten by the next save."""
    save_traveller(cfg, 7, doc(1))
    path = traveller_path(cfg, 7)
    files.previous(path).write_text('{"entity_id": 7, "ste' + "#" * 5000)
    assert read_traveller(cfg, 7) == doc(1)
    save_traveller(cfg, 7, doc(2))
    assert read_traveller(cfg, 7) == doc(2)


def test_a_file_system_that_cannot_swap_gets_a_new_file_renamed_over(
    cfg: Config, monkeypatch: pytest.MonkeyPatch
) -> None:
    def cannot(a: Path, b: Path) -> None:
        raise OSError(errno.EINVAL, "Invalid argument")

    monkeypatch.setattr(files, "_exchange", cannot)
    for n in (1, 2, 3):
        save_traveller(cfg, 7, doc(n))
        assert read_traveller(cfg, 7) == doc(n)


def test_another_failure_of_the_swap_is_not_hidden(cfg: Config, monkeypatch: pytest.MonkeyPatch) -> None:
    def denied(a: Path, b: Path) -> None:
        raise OSError(errno.EACCES, "Permission denied")

    save_traveller(cfg, 7, doc(1))
    monkeypatch.setattr(files, "_exchange", denied)
    with pytest.raises(PermissionError):
        save_traveller(cfg, 7, doc(2))
    assert read_traveller(cfg, 7) == doc(1)  # the traveller as it was
