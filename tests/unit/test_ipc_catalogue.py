"""The Conversation Tool: the catalogue is consistent, validates messages, and documents itself."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from gwc.errors import MessageError
from gwc.hi.monitor import render_catalogue
from gwc.ipc import catalogue
from gwc.ipc.catalogue import check, message
from gwc.ipc.namegen import render_names
from gwc.ipc.names import Conv, Msg

DOC = Path(__file__).resolve().parents[2] / "docs" / "conversations.md"


def test_every_conversation_names_known_messages_and_opens_with_its_first() -> None:
    for c in catalogue.CONVERSATION_CLASSES.values():
        assert c.messages, c.name
        assert all(m in catalogue.MESSAGE_CLASSES for m in c.messages), c.name
        assert len(c.name) <= 20 and c.doc


def test_message_checks_required_nullable_and_types() -> None:
    m = message("Machine_Request", entity_id=4, op_type="mill", num_machines=2)
    assert m.priority is None and m.entity_id == 4  # a declared nullable field reads as None
    with pytest.raises(MessageError, match="required"):
        message("Machine_Request", entity_id=4, op_type="mill")
    with pytest.raises(MessageError, match="must be int"):
        message("Machine_Request", entity_id="4", op_type="mill", num_machines=2)
    with pytest.raises(MessageError, match="must be int"):
        message("Machine_Request", entity_id=True, op_type="mill", num_machines=2)  # a bool is not an int
    with pytest.raises(MessageError, match="unknown field"):
        message("Ping", n=1, color="red")
    with pytest.raises(MessageError, match="unknown message class"):
        message("Nope")
    assert message("Change_Status", machine_id="wc1", status="Idle", note=None).fields == {
        "machine_id": "wc1",
        "status": "Idle",
    }


def test_received_messages_must_belong_to_their_conversation() -> None:
    assert check("PING", "Ping", {"n": 1}).n == 1
    with pytest.raises(MessageError, match="does not belong"):
        check("PING", "Machine_Entry", {"machine_id": "x"})
    with pytest.raises(MessageError, match="unknown conversation class"):
        check("NOPE", "Ping", {"n": 1})
    with pytest.raises(AttributeError):
        _ = check("PING", "Ping", {"n": 1}).nothing


def test_ack_codes_are_spelled_as_the_thesis_spells_them() -> None:
    from gwc.ipc.codes import AckCode

    assert AckCode.NOT_RESERVED == "Not_Reserv" and AckCode.ACK_OK == "ACK_OK"


def test_docs_conversations_md_is_generated_from_the_catalogue() -> None:
    assert DOC.read_text() == render_catalogue(), (
        "docs/conversations.md is out of date: run `gwc monitor --catalogue > docs/conversations.md`"
    )


def test_names_py_is_generated_from_the_catalogue() -> None:
    """gwc/ipc/names.py (Conv, Msg) names exactly the catalogue's classes: regenerate it after a change."""
    names = Path(__file__).resolve().parents[2] / "gwc" / "ipc" / "names.py"
    assert names.read_text() == render_names(), (
        "gwc/ipc/names.py is stale: python -m gwc.ipc.namegen > gwc/ipc/names.py"
    )


def test_code_names_conversations_and_messages_by_conv_and_msg() -> None:
    """No string literal in gwc/ spells a conversation class or message name (docstrings and f-strings
    aside): code says Conv.X / Msg.X, so a misspelling fails in mypy rather than in a conversation."""
    names = {c.value for c in Conv} | {m.value for m in Msg}
    root = Path(__file__).resolve().parents[2] / "gwc"
    found = []
    for path in sorted(root.rglob("*.py")):
        if path.name in ("names.py", "catalogue.py"):  # where the names are defined
            continue
        tree = ast.parse(path.read_text())
        skip = {id(n) for n in ast.walk(tree) if isinstance(n, ast.JoinedStr)}
        skip |= {id(v) for n in ast.walk(tree) if isinstance(n, ast.JoinedStr) for v in n.values}
        for node in ast.walk(tree):
            if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
                body = node.body
                if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                    skip.add(id(body[0].value))
        for node in ast.walk(tree):
            if isinstance(node, ast.Constant) and node.value in names and id(node) not in skip:
                found.append(f"{path.relative_to(root.parent)}:{node.lineno} {node.value!r}")
    assert not found, "use gwc.ipc.names.Conv / Msg:\n" + "\n".join(found)
