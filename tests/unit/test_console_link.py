"""The console's link, without a cell: what it listens for and how it words the cell's answers."""

from __future__ import annotations

from gwc.console.link import VIEWS_OF, in_words
from gwc.ipc import catalogue
from gwc.ipc.codes import AckCode


def test_every_class_the_console_listens_for_is_in_the_catalogue() -> None:
    assert set(VIEWS_OF) <= set(catalogue.CONVERSATION_CLASSES)


def test_every_ack_code_is_said_in_words() -> None:
    for code in AckCode:
        assert in_words(code.value).startswith(f"{code.value} (") and len(code.words) > 3
    assert in_words("NOT_A_CODE") == "NOT_A_CODE"
