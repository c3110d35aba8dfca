"""The shape of the code (docs/architecture.md, *Objects that hold their parts*): the layer rule (no module
imports from a layer above its own; the table is read from the page itself, so the page and the rule
cannot drift); no import cycle at run time; no class over 45 methods counted over its gwc ancestry (a
chain of classes is one object); no reaching into another package's private attributes. A file's length
is reported, not failed (issue 37): size follows the subject.
"""

from __future__ import annotations

import ast
import functools
import re
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "architecture.md"
ROW = re.compile(r"^\|\s*(\d+)\s*\|([^|]*)\|")
MAX_LINES = 700
MAX_METHODS = 45


def layer_table() -> dict[str, int]:
    """Module name prefix -> layer, from the page's table."""
    table = {}
    for line in DOC.read_text().splitlines():
        m = ROW.match(line)
        if m:
            for name in re.findall(r"`([\w.]+)`", m.group(2)):
                table[name] = int(m.group(1))
    return table


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imports(source: str, name: str, is_package: bool = False) -> list[tuple[int, str]]:
    """(line, module) of every gwc import in the source of module `name`, function-level ones too, relative
    ones resolved, `from gwc import x` as gwc.x."""
    package = name.split(".") if is_package else name.split(".")[:-1]
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package[: len(package) - node.level + 1] + ([base] if base else []))
            if base == "gwc" or not node.module:
                found += [(node.lineno, f"{base}.{a.name}") for a in node.names]
            else:
                found.append((node.lineno, base))
    return [(line, m) for line, m in found if m == "gwc" or m.startswith("gwc.")]


def imports_of(path: Path) -> list[tuple[int, str]]:
    return imports(path.read_text(), module_name(path), path.name == "__init__.py")


def layer_of(name: str, table: dict[str, int]) -> int | None:
    best = max((p for p in table if name == p or name.startswith(p + ".")), key=len, default=None)
    return None if best is None else table[best]


def test_the_layer_table_places_every_module() -> None:
    table = layer_table()
    assert table, f"no layer table found in {DOC}"
    unplaced = [module_name(p) for p in sorted((ROOT / "gwc").rglob("*.py")) if layer_of(module_name(p), table) is None]
    assert not unplaced, f"modules not in the layer table of docs/architecture.md (add a row): {unplaced}"


def test_no_module_imports_from_a_layer_above_its_own() -> None:
    table = layer_table()
    upward = []
    for path in sorted((ROOT / "gwc").rglob("*.py")):
        mine = layer_of(module_name(path), table)
        if mine is None:
            continue
        for line, target in imports_of(path):
            theirs = layer_of(target, table)
            if theirs is not None and theirs > mine:
                upward.append(f"{path.relative_to(ROOT)}:{line} (layer {mine}) imports {target} (layer {theirs})")
    assert not upward, "imports from a higher layer (docs/architecture.md):\n" + "\n".join(upward)


def test_the_checker_sees_relative_and_function_level_imports() -> None:
    src = "from . import wire\nfrom .bus import Bus\nimport os\ndef f():\n    from gwc.client import orders\n"
    assert [m for _, m in imports(src, "gwc.ipc.probe")] == ["gwc.ipc.wire", "gwc.ipc.bus", "gwc.client"]
    assert [m for _, m in imports("from .. import db\n", "gwc.ipc", is_package=True)] == ["gwc.db"]


# ----------------------------------------------------------------------------- the code, read once


def gwc_files() -> list[Path]:
    return sorted((ROOT / "gwc").rglob("*.py"))


def package_of(path: Path) -> str:
    """The package a file belongs to: its directory (gwc/wc/steps.py -> gwc.wc; gwc/module.py -> gwc)."""
    return ".".join(path.relative_to(ROOT).parent.parts)


@functools.cache
def parsed() -> dict[str, tuple[Path, ast.Module]]:
    return {module_name(p): (p, ast.parse(p.read_text())) for p in gwc_files()}


def is_type_checking(node: ast.AST) -> bool:
    return isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)


def runtime_imports(tree: ast.Module, name: str, is_package: bool, known: set[str]) -> set[str]:
    """The gwc modules this one imports when it runs: module-level and function-level imports alike
    (a function's import runs when it is called), those under `if TYPE_CHECKING:` aside. `from p import
    x` counts as p.x when that is a module, else as p."""
    package = name.split(".") if is_package else name.split(".")[:-1]
    found: set[str] = set()

    def visit(node: ast.AST) -> None:
        for child in ast.iter_child_nodes(node):
            if is_type_checking(child):
                for sub in getattr(child, "orelse", []):
                    visit(sub)
                continue
            if isinstance(child, ast.Import):
                found.update(a.name for a in child.names if a.name in known)
            elif isinstance(child, ast.ImportFrom):
                base = child.module or ""
                if child.level:
                    base = ".".join(package[: len(package) - child.level + 1] + ([base] if base else []))
                for a in child.names:
                    target = f"{base}.{a.name}" if f"{base}.{a.name}" in known else base
                    if target in known and target != name:
                        found.add(target)
            visit(child)

    visit(tree)
    return found


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected parts of the import graph with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def strong(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            part = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                part.append(w)
                if w == v:
                    break
            if len(part) > 1:
                cycles.append(sorted(part))

    for v in sorted(graph):
        if v not in index:
            strong(v)
    return cycles


# ----------------------------------------------------------------------------- classes and their ancestry


class ClassInfo:
    """A gwc class as the AST has it: its methods, the private names it defines, its gwc bases."""

    def __init__(self, qualname: str, path: Path, node: ast.ClassDef, bases: list[str]) -> None:
        self.qualname = qualname
        self.path = path
        self.methods = {f.name for f in node.body if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))}
        self.bases = bases
        self.private = {n for n in defined_names(node) if is_private(n)}


def is_private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def defined_names(node: ast.ClassDef) -> set[str]:
    """Names a class defines: its methods and class attributes, and what its methods assign to self."""
    names: set[str] = set()
    for item in node.body:
        if isinstance(item, (ast.FunctionDef, ast.AsyncFunctionDef)):
            names.add(item.name)
        elif isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name):
            names.add(item.target.id)
        elif isinstance(item, ast.Assign):
            names.update(t.id for t in item.targets if isinstance(t, ast.Name))
    for sub in ast.walk(node):
        if isinstance(sub, ast.Attribute) and isinstance(sub.ctx, ast.Store) and ast.unparse(sub.value) == "self":
            names.add(sub.attr)
    return names


@functools.cache
def classes() -> dict[str, ClassInfo]:
    """Every class in gwc/, by qualified name (gwc.wc.wc.WC), its bases resolved to gwc classes."""
    return classes_of(parsed())


def classes_of(trees: dict[str, tuple[Path, ast.Module]]) -> dict[str, ClassInfo]:
    found: dict[str, tuple[Path, ast.ClassDef, str, dict[str, str]]] = {}
    for name, (path, tree) in trees.items():
        imported: dict[str, str] = {}  # local name -> what it names
        package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
        for node in tree.body:
            if isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    base = ".".join(package[: len(package) - node.level + 1] + ([base] if base else []))
                for a in node.names:
                    imported[a.asname or a.name] = f"{base}.{a.name}"
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef):
                found[f"{name}.{node.name}"] = (path, node, name, imported)
    infos = {}
    for qualname, (path, node, module, imported) in found.items():
        bases = []
        for b in node.bases:
            target = b.value if isinstance(b, ast.Subscript) else b  # Generic[T], Protocol[T]
            text = ast.unparse(target)
            head = text.split(".")[0]
            for candidate in (f"{module}.{text}", f"{imported.get(head, head)}{text[len(head) :]}"):
                if candidate in found:
                    bases.append(candidate)
                    break
        infos[qualname] = ClassInfo(qualname, path, node, bases)
    return infos


def ancestry(qualname: str, infos: dict[str, ClassInfo]) -> list[ClassInfo]:
    """The class and every gwc class it derives from."""
    seen: dict[str, ClassInfo] = {}
    todo = [qualname]
    while todo:
        q = todo.pop()
        if q not in seen:
            seen[q] = infos[q]
            todo.extend(infos[q].bases)
    return list(seen.values())


# ----------------------------------------------------------------------------- the rules

# Classes over the bound when it was first counted over the ancestry (issue 37), not yet cut into parts:
# each may shrink, none may grow (its count here is its ceiling), and none joins them. Module's database
# half (gwc/moduledb.py) and its lifecycle (module.Lifecycle) are parts now: Module counts 27 methods.
OVER_UNTIL_CUT: dict[str, int] = {}


def test_no_class_over_45_methods_counted_over_its_gwc_ancestry() -> None:
    """A class's size is a design fact, and a chain of classes is one object: its methods are counted
    over every gwc class it derives from (an override counts once)."""
    infos = classes()
    big = []
    for q, info in sorted(infos.items()):
        methods = set().union(*(c.methods for c in ancestry(q, infos)))
        if len(methods) > OVER_UNTIL_CUT.get(q, MAX_METHODS):
            chain = " <- ".join(c.qualname.rsplit(".", 1)[1] for c in ancestry(q, infos))
            big.append(f"{info.path.relative_to(ROOT)}: {chain}: {len(methods)} methods")
    assert not big, f"over {MAX_METHODS} methods: hold parts instead (docs/architecture.md):\n" + "\n".join(big)


def test_the_method_count_follows_the_ancestry() -> None:
    infos = classes()
    wc = {m for c in ancestry("gwc.wc.wc.WC", infos) for m in c.methods}
    assert "transaction_when_up" in wc and "setup_run" in wc, "WC's count includes gwc.module.Module's methods"


def test_no_import_cycle_at_run_time() -> None:
    """No two gwc modules import each other, directly or round a ring, when they run: function-level
    imports count (they run when called), `if TYPE_CHECKING:` imports do not."""
    trees = parsed()
    known = set(trees)
    graph = {
        name: runtime_imports(tree, name, path.name == "__init__.py", known) for name, (path, tree) in trees.items()
    }
    cycles = import_cycles(graph)
    assert not cycles, "import cycles (move what both need below both):\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_the_cycle_finder_sees_function_level_imports_and_skips_type_only_ones() -> None:
    a = ast.parse("from gwc.b import f\n")
    b = ast.parse("def g():\n    from gwc.a import x\n")
    c = ast.parse("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from gwc.a import y\n")
    known = {"gwc.a", "gwc.b", "gwc.c"}
    graph = {
        "gwc.a": runtime_imports(a, "gwc.a", False, known) | {"gwc.c"},
        "gwc.b": runtime_imports(b, "gwc.b", False, known),
        "gwc.c": runtime_imports(c, "gwc.c", False, known),
    }
    assert import_cycles(graph) == [["gwc.a", "gwc.b"]]


def private_reaches(
    infos: dict[str, ClassInfo], trees: dict[str, tuple[Path, ast.Module]]
) -> list[tuple[str, int, str]]:
    """(file, line, expression) of every read or write of a private attribute (`x._name`) that belongs
    to a gwc class of another package: `self._name` when the gwc class defining it in the reader's
    ancestry lives in another package; `other._name` when only classes of other packages define it."""
    by_name: dict[str, set[str]] = {}  # private name -> packages whose classes define it
    for info in infos.values():
        for n in info.private:
            by_name.setdefault(n, set()).add(package_of(info.path))
    reaches = []
    for name, (path, tree) in trees.items():
        package = package_of(path)
        for cls in [n for n in ast.walk(tree) if isinstance(n, ast.ClassDef)] + [tree]:
            mine = ancestry(f"{name}.{cls.name}", infos) if isinstance(cls, ast.ClassDef) else []
            body = (
                cls.body if isinstance(cls, ast.ClassDef) else [n for n in tree.body if not isinstance(n, ast.ClassDef)]
            )
            for node in (n for item in body for n in ast.walk(item)):
                if not isinstance(node, ast.Attribute) or not is_private(node.attr):
                    continue
                if isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"):
                    owners = {package_of(c.path) for c in mine if node.attr in c.private}
                else:
                    owners = by_name.get(node.attr, set())
                if owners and package not in owners:
                    reaches.append((str(path.relative_to(ROOT)), node.lineno, ast.unparse(node)))
    return reaches


def test_no_private_attribute_of_another_packages_class_is_reached() -> None:
    """Files talk through public interfaces (docs/architecture.md): no module reads or writes a private
    attribute of a class of another package (its own package's are its own business)."""
    reaches = private_reaches(classes(), parsed())
    assert not reaches, "private attributes of another package's class:\n" + "\n".join(
        f"{f}:{line}: {expr}" for f, line, expr in reaches
    )


def test_long_files_are_reported_not_failed() -> None:
    """A file's length is not a design fact (issue 37): files over 700 lines are reported (a warning in
    the test summary), never failed."""
    long = []
    for path in gwc_files():
        if (n := path.read_text().count("\n")) > MAX_LINES:
            long.append(f"{path.relative_to(ROOT)}: {n} lines")
    if long:
        warnings.warn("files over 700 lines (split where a seam shows): " + "; ".join(long), stacklevel=1)


def test_the_private_reach_finder_sees_other_packages_attributes_only() -> None:
    sources = {
        "gwc.a.m": "class A:\n    def __init__(self):\n        self._x = 1\n"
        "    def _f(self):\n        return self._x\n",
        "gwc.a.n": "def g(a):\n    return a._x\n",  # its own package's: its business
        "gwc.b.m": (
            "from gwc.a.m import A\n"
            "class B(A):\n    def h(self):\n        return self._x\n"  # A's, of another package
            "class C:\n    def __init__(self):\n        self._y = 2\n"
            "    def k(self, a):\n        return a._f(), self._y\n"
        ),
    }
    trees = {n: (ROOT / (n.replace(".", "/") + ".py"), ast.parse(src)) for n, src in sources.items()}
    found = {(f, expr) for f, _, expr in private_reaches(classes_of(trees), trees)}
    assert found == {("gwc/b/m.py", "self._x"), ("gwc/b/m.py", "a._f")}
