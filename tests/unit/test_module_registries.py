"""The registries that name code by string (modules, machine processes, ME kinds) name code that exists:
a misspelt entry fails here, not when a cell starts that process."""

from __future__ import annotations

import importlib
from typing import Any

import pytest

from gwc.config import ME_KINDS
from gwc.me.machine import MachineSide
from gwc.module import BUS_MODULES, MACHINE_PROCESSES, Module


def load(path: str) -> Any:
    module, _, attr = path.partition(":")
    return getattr(importlib.import_module(module), attr)


@pytest.mark.parametrize("name", sorted(BUS_MODULES))
def test_every_bus_module_is_a_module(name: str) -> None:
    assert issubclass(load(BUS_MODULES[name]), Module)


@pytest.mark.parametrize("name", sorted(MACHINE_PROCESSES))
def test_every_machine_process_has_its_main(name: str) -> None:
    assert callable(load(MACHINE_PROCESSES[name]))


@pytest.mark.parametrize("kind", sorted(ME_KINDS))
def test_every_me_kind_is_a_machine_side(kind: str) -> None:
    assert issubclass(load(ME_KINDS[kind]), MachineSide)
