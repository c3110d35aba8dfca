"""gwc.lot's public API, the one lot scripts are written against, stays as it is (issue 37: the entity
was recut into parts under it): the names gwc.lot exports, every public call of OperationEntity with
its signature as it was before the recut, its attributes (read and set: `entity.timeouts = ...` reaches
every part), and every `entity.<name>` that a lot script in the repository or in docs/lot-scripts.md
uses."""

from __future__ import annotations

import ast
import inspect
import logging
import re
from pathlib import Path

import gwc.lot
from gwc.lot import OperationEntity, Timeouts
from tests.conftest import make_config

ROOT = Path(__file__).resolve().parents[2]

EXPORTS = [
    "LotError",
    "LotTimeout",
    "MachineDied",
    "MachineLost",
    "MachineRequest",
    "Operation",
    "OperationEntity",
    "RequestCancelled",
    "RequestRefused",
    "Reservation",
    "Run",
    "RunFailed",
    "RunInDoubt",
    "ScriptStopped",
    "StepRefused",
    "Timeouts",
    "create_lot",
    "read_traveller",
    "traveller_path",
    "verdict",
]

# OperationEntity's calls and their signatures before the recut (main at a70ee41: the six-class chain).
SIGNATURES = {
    "__enter__": "(self) -> 'OperationEntity'",
    "__exit__": "(self, exc_type: 'type[BaseException] | None', exc: 'BaseException | None', tb: 'Any') -> 'None'",
    "__init__": "(self, cfg: 'Config', entity_id: 'int', log: 'logging.Logger', timeouts: 'Timeouts | None' = None, max_tries: 'int' = 3) -> 'None'",  # noqa: E501
    "cancel_requests": "(self, request_key: 'int | None' = None, timeout: 'float | None' = None, within: 'float | None' = None) -> 'int'",  # noqa: E501
    "close": "(self) -> 'None'",
    "divide": "(self, quantity: 'int' = 1, start_scripts: 'bool' = True) -> 'list[int]'",
    "download_recipe": "(self, machine_id: 'str', recipe_id: 'str') -> 'None'",
    "entity_request": "(self, action: 'str', reason: 'str | None' = None, script_pid: 'int | None' = None, timeout: 'float | None' = None, within: 'float | None' = None) -> 'Message'",  # noqa: E501
    "fail": "(self, reason: 'str') -> 'None'",
    "lot_completed": "(self, result: 'str | None' = None) -> 'None'",
    "merge": "(self, child: 'int') -> 'None'",
    "open": "(self) -> 'None'",
    "operate": "(self, op_type: 'str', alternatives: 'Sequence[Sequence[str]] | None' = None, recipes: 'str | dict[str, str] | None' = None, priority: 'int | None' = None) -> 'Operation'",  # noqa: E501
    "propose_recipe": "(self, recipe_id: 'str', content: 'str') -> 'int'",
    "qualified_machines": "(self, op_type: 'str', up_only: 'bool' = True) -> 'list[str]'",
    "read_state": "(self) -> 'str | None'",
    "recipe_for": "(self, machine_id: 'str', op_type: 'str') -> 'str'",
    "report": "(self, action: 'str') -> 'None'",
    "request_machines": "(self, op_type: 'str', alternatives: 'Sequence[Sequence[str]]', priority: 'int | None' = None) -> 'MachineRequest'",  # noqa: E501
    "reserve": "(self, op_type: 'str', alternatives: 'Sequence[Sequence[str]] | None' = None, priority: 'int | None' = None, timeout: 'float | None' = None) -> 'Reservation'",  # noqa: E501
    "run_on": "(self, reservation: 'Reservation', recipes: 'str | dict[str, str] | None' = None) -> 'list[Run]'",
    "run_results": "(self, machine_id: 'str', machine_run_id: 'int') -> 'dict[str, str]'",
    "scrap": "(self, machine_id: 'str', machine_run_id: 'int', parts: 'int' = 1, reason: 'str | None' = None) -> 'None'",  # noqa: E501
    "setup_run": "(self, machine_id: 'str', recipe_id: 'str | None', op_type: 'str', machine_run_id: 'int', start: 'bool' = False) -> 'str'",  # noqa: E501
    "start_child": "(self, product_id: 'str', quantity: 'int' = 1, script_id: 'str | None' = None) -> 'list[int]'",
    "start_run": "(self, machine_id: 'str', machine_run_id: 'int') -> 'None'",
    "unreserve": "(self, machine_id: 'str | None' = None, timeout: 'float | None' = None, within: 'float | None' = None) -> 'int'",  # noqa: E501
    "unreserve_soon": "(self, machine_id: 'str | None' = None, timeout: 'float | None' = None, within: 'float | None' = None) -> 'Callable[[], int]'",  # noqa: E501
    "upload_recipe": "(self, machine_id: 'str', recipe_id: 'str') -> 'int'",
    "wait_for_children": "(self, children: 'Sequence[int]', timeout: 'float | None' = None) -> 'dict[int, str]'",
    "wait_for_export": "(self, timeout: 'float | None' = None) -> 'None'",
    "wait_for_import": "(self, timeout: 'float | None' = None) -> 'None'",
    "wait_for_machines": "(self, request: 'MachineRequest', timeout: 'float | None' = None) -> 'Reservation'",
    "wait_run_complete": "(self, machine_run_id: 'int', machines: 'Sequence[str]', timeout: 'float | None' = None) -> 'dict[str, str]'",  # noqa: E501
}
ATTRIBUTES = [
    "cfg",
    "entity_id",
    "name",
    "log",
    "timeouts",
    "max_tries",
    "in_doubt",
    "lot_id",
    "state",
    "product_id",
    "priority",
    "work_order_id",
    "script_id",
    "script_path",
    "result",
    "traveller",
]


def test_gwc_lot_exports_what_it_did() -> None:
    assert sorted(gwc.lot.__all__) == EXPORTS


def test_every_call_of_the_entity_keeps_its_signature() -> None:
    now = {
        name: str(inspect.signature(getattr(OperationEntity, name)))
        for name in SIGNATURES
        if callable(getattr(OperationEntity, name, None))
    }
    assert now == SIGNATURES


def test_the_entity_attributes_are_read_and_set_as_before(tmp_path: Path) -> None:
    entity = OperationEntity(make_config(tmp_path, None), 7, logging.getLogger("lot-api"))
    for name in ATTRIBUTES:
        getattr(entity, name)
    assert (entity.entity_id, entity.name, entity.state, entity.in_doubt) == (7, "lot:7", None, "hold")
    entity.timeouts = Timeouts(answer=1.5)
    entity.in_doubt = "reroute"
    entity.lot_id = 3
    assert entity.facts.timeouts.answer == 1.5 and entity.runs.facts.in_doubt == "reroute"
    assert entity.link.facts.lot_id == 3  # one state, every part


def scripts() -> dict[str, str]:
    """Every lot script's source: the shipped ones, the tests' own (files, and strings written out as
    scripts), and docs/lot-scripts.md's examples."""
    found = {str(p.relative_to(ROOT)): p.read_text() for p in sorted((ROOT / "gwc" / "lot" / "scripts").glob("*.py"))}
    for p in sorted((ROOT / "tests").rglob("*.py")):
        if p == Path(__file__).resolve():
            continue
        text = p.read_text()
        tree = ast.parse(text)
        if any(isinstance(f, ast.FunctionDef) and f.name == "main" for f in tree.body):
            found[str(p.relative_to(ROOT))] = text
        for i, node in enumerate(ast.walk(tree)):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and "def main(entity" in node.value:
                found[f"{p.relative_to(ROOT)}:{i}"] = node.value
    doc = (ROOT / "docs" / "lot-scripts.md").read_text()
    found.update({f"docs/lot-scripts.md:{i}": s for i, s in enumerate(re.findall(r"```python\n(.*?)```", doc, re.S))})
    return found


def test_every_lot_script_in_the_repo_and_the_docs_uses_only_what_the_entity_has() -> None:
    missing = []
    sources = scripts()
    assert any(k.startswith("docs/lot-scripts.md") for k in sources) and any(
        k.startswith("gwc/lot/scripts") for k in sources
    )
    for where, source in sources.items():
        try:
            tree = ast.parse(source)
        except SyntaxError:  # a fragment of a page: its names are still read below
            names = set(re.findall(r"\bentity\.(\w+)", source))
        else:
            names = {
                n.attr
                for n in ast.walk(tree)
                if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Name) and n.value.id == "entity"
            }
        missing += [f"{where}: entity.{n}" for n in sorted(names) if not hasattr(OperationEntity, n)]
    assert not missing, missing
