"""The Figure 2 log files: one entry a line, rotated at their size cap."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import pytest

from gwc import log as gwc_log


def test_a_log_rotates_at_its_cap_keeps_its_backups_and_loses_no_entry(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(gwc_log, "MAX_LOG_BYTES", 4000)
    logger = gwc_log.open_log("wc:capped", tmp_path)
    try:
        for i in range(200):
            logger.info("entry %03d %s", i, "x" * 40)
    finally:
        for h in logger.handlers:
            h.close()
    files = sorted(tmp_path.glob("wc-capped.log*"))
    assert [f.name for f in files] == [f"wc-capped.log{s}" for s in ("", ".1", ".2", ".3")]
    # Each file passes the cap by one entry at most.
    assert all(f.stat().st_size < 4000 + 300 for f in files)
    lines = [line for f in reversed(files[1:]) for line in f.read_text().splitlines()]
    lines += files[0].read_text().splitlines()
    numbers = [int(line.split("Note: entry ")[1][:3]) for line in lines]
    assert numbers == list(range(numbers[0], 200))  # the newest, in order, none lost between files
    assert all("| Module wc:capped |" in line for line in lines)


def test_a_log_that_is_not_a_regular_file_is_written_not_rotated(tmp_path: Path) -> None:
    (tmp_path / "wc-fifo.log").symlink_to("/dev/null")
    logger = gwc_log.open_log("wc:fifo", tmp_path)
    try:
        logging.getLogger("gwc.wc:fifo").info("x" * 100)
    finally:
        for h in logger.handlers:
            h.close()
    assert not list(tmp_path.glob("wc-fifo.log.*"))


def test_a_process_out_file_is_bounded_and_moved_aside_at_the_next_start(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(gwc_log, "MAX_OUT_BYTES", 1000)
    out = tmp_path / "wc-x.out"
    with open(gwc_log.open_out(out), "w") as f:
        capped = gwc_log.CappedStream(f, 1000)  # type: ignore[arg-type]
        for _ in range(500):
            capped.write("Traceback (most recent call last): ...\n")
    assert 1000 <= out.stat().st_size < 1200 and "dropped" in out.read_text()
    os.close(gwc_log.open_out(out))  # the next start: the full file moves aside
    assert not out.stat().st_size and (tmp_path / "wc-x.out.1").stat().st_size >= 1000
    (tmp_path / "evil.out").symlink_to(tmp_path / "target")
    with pytest.raises(OSError):
        gwc_log.open_out(tmp_path / "evil.out")  # never written through a link
    assert not (tmp_path / "target").exists()


def test_every_control_character_in_a_field_is_escaped_so_no_line_can_be_forged(tmp_path: Path) -> None:
    logger = gwc_log.open_log("ms", tmp_path)
    try:
        with gwc_log.conversation("c.1\nFrom forged | Error: x", "CANCEL_RE"):
            logger.info("by %s", "a\rb\x1b[2J\x9b\x7f\t\x00")
        try:
            raise ValueError("two\nlines")
        except ValueError:
            logger.exception("failed")
    finally:
        for h in logger.handlers:
            h.close()
    lines = (tmp_path / "ms.log").read_text().splitlines()
    assert len(lines) == 2 and all(line.startswith("From ") for line in lines)
    assert "Conv c.1\\nFrom forged | Error: x CANCEL_RE" in lines[0]
    assert lines[0].endswith("by a\\rb\\x1b[2J\\x9b\\x7f\\t\\x00")
    assert "ValueError: two | lines" in lines[1]  # a traceback's lines joined on one
    assert gwc_log.escape("plain text, ünïcode") == "plain text, ünïcode"
