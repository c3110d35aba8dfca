"""gwc/ipc/names.py, written from the catalogue: the conversation and message names as str enums, so
that a misspelt name fails at import (and in mypy and ruff), not in a conversation at run time.
`python -m gwc.ipc.namegen > gwc/ipc/names.py`; tests/unit/test_ipc_catalogue.py fails when they differ."""

from __future__ import annotations

import sys

from gwc.ipc.catalogue import CONVERSATION_CLASSES, MESSAGE_CLASSES

NAMES_HEADER = '''"""Conversation classes and message names as constants, so that a misspelt name fails at import
(and in mypy and ruff), not in a conversation at run time. Generated from the catalogue (gwc/ipc/catalogue.py)
by gwc/ipc/namegen.py: do not edit; write it again with `python -m gwc.ipc.namegen > gwc/ipc/names.py`.
tests/unit/test_ipc_catalogue.py fails when it and the catalogue differ.

They are str enums: `Conv.MACH_REQ == "MACH_REQ"`, and they go on the wire as the thesis spells them.
"""

from enum import StrEnum
'''


def render_names() -> str:
    """The source of gwc/ipc/names.py for this catalogue."""
    lines = [NAMES_HEADER, "", "class Conv(StrEnum):", '    """The conversation classes."""', ""]
    lines += [f'    {name} = "{name}"' for name in sorted(CONVERSATION_CLASSES)]
    lines += ["", "", "class Msg(StrEnum):", '    """The message classes."""', ""]
    lines += [f'    {name.upper()} = "{name}"' for name in sorted(MESSAGE_CLASSES, key=str.upper)]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.stdout.write(render_names())
