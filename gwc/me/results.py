"""The results file an ME writes at the end of a run and its WC loads into MACHINE_RUN_RESULT.

Listing 3 read it with `fscanf("%s")` pairs: a parameter, then its value. We keep one pair per
line, `PARAM value`, the value being the rest of the line (so it may hold spaces); blank lines and
lines starting with `#` are skipped. A line with no value or a parameter given twice makes the
whole file invalid: a results file is evidence, and half of it is worse than a clear error.
The file is written to a temporary name and renamed, so the WC never reads half a file.

The ME also records in it, as a `# outcome` comment line, how the run ended (the ack code and note
of its RUN_COMPL): a WC restarted after its predecessor read RUN_COMPL and died before storing the
results completes the run from the file alone, exactly as RUN_COMPL would have (read_outcome).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

OUTCOME = "# outcome "  # the comment line that carries the run's ack code and note


def read_results(path: Path | str) -> dict[str, str]:
    """The param/value pairs of a results file, in file order; ValueError saying which line is wrong."""
    results: dict[str, str] = {}
    for n, line in enumerate(Path(path).read_text(encoding="utf-8").splitlines(), 1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        param, _, value = text.partition(" ")
        value = value.strip()
        if not value:
            raise ValueError(f"{path} line {n}: parameter {param!r} has no value")
        if param in results:
            raise ValueError(f"{path} line {n}: parameter {param!r} given twice")
        results[param] = value
    return results


def read_outcome(path: Path | str) -> tuple[str, str] | None:
    """The (ack code, note) the ME recorded for its run, or None if the file records none."""
    for line in Path(path).read_text(encoding="utf-8").splitlines():
        if line.startswith(OUTCOME):
            code, _, note = line[len(OUTCOME) :].strip().partition(" ")
            return code, note.strip()
    return None


def write_results(path: Path | str, results: Mapping[str, object], outcome: tuple[str, str] | None = None) -> Path:
    """Write param/value pairs atomically; ValueError for a parameter the reader could not read back.

    `outcome` (ack code, note) is how the run ended, recorded for read_outcome.
    """
    path = Path(path)
    lines = []
    if outcome is not None:
        code, note = outcome
        if not code or any(c.isspace() for c in code):
            raise ValueError(f"run outcome {code!r} must be one word")
        lines.append(f"{OUTCOME}{code} {' '.join(note.split())}".rstrip() + "\n")
    for param, value in results.items():
        text = str(value)
        if not param or any(c.isspace() for c in param) or param.startswith("#"):
            raise ValueError(f"results parameter {param!r} must be one word")
        if not text.strip() or "\n" in text:
            raise ValueError(f"results value of {param} must be one non-empty line, got {text!r}")
        lines.append(f"{param} {text.strip()}\n")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text("".join(lines), encoding="utf-8")
    os.replace(tmp, path)
    return path
