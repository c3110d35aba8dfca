"""A rolling upgrade while lots run (issue 36, item 4): MSCHED and the Lot Server, each with a standby,
moved host by host to a second build whose wire version is one higher (with one new optional message
field) and whose schema version is one higher (with one additive migration). No lot fails, nothing is
run twice, `gwc check` is clean, and the Conversation Monitor shows modules of both versions talking.

The second build is real: this checkout's gwc/, sql/ and pyproject.toml copied to a folder of the test's
and patched there; a process runs it with PYTHONPATH naming that folder. The hosts are process groups
on this one host, not network-namespace hosts (the lease does not care where instances run, and
namespaces would double the test's time): "h1" runs the active instances at first, "h2" their
standbys, the machines and the other servers are not upgraded here (docs/deploying.md, 7)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from gwc.config import PROJECT_ROOT
from gwc.ipc import wire
from gwc.ipc.catalogue import message
from gwc.ipc.codes import AckCode
from gwc.schema import SCHEMA_VERSION
from tests.e2e.lotkit import cell_with_machines, gwc, import_export_all, ok, order, stop_lot_scripts, wait_state
from tests.e2e.test_redundancy import LEASED, Standbys, holder, leased_cell, no_run_twice, standing_by
from tests.harness import CellHarness, wait_for
from tests.leaks import MARK

pytestmark = pytest.mark.e2e

NEW_WIRE = wire.VERSION + 1
NEW_SCHEMA = SCHEMA_VERSION + 1


def patch(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert text.count(old) == 1, f"{path.name}: the upgrade test's patch no longer applies at {old!r}"
    path.write_text(text.replace(old, new))


def second_build(where: Path) -> Path:
    """This build, copied and patched: wire VERSION + 1 (reading this one's too), one new optional field
    (Startup_Ack's `build`, which the new build sends), schema version + 1 by an additive migration."""
    root = where / "build2"
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "node_modules")
    shutil.copytree(PROJECT_ROOT / "gwc", root / "gwc", ignore=ignore)
    shutil.copytree(PROJECT_ROOT / "sql", root / "sql")
    shutil.copy(PROJECT_ROOT / "pyproject.toml", root / "pyproject.toml")  # (gwc.config.from_checkout)
    patch(
        root / "gwc" / "ipc" / "wire.py",
        f"VERSION = {wire.VERSION}\nMIN_VERSION = {wire.MIN_VERSION}\n",
        f"VERSION = {NEW_WIRE}\nMIN_VERSION = {wire.VERSION}\n",
    )
    patch(
        root / "gwc" / "ipc" / "catalogue.py",
        '_msg("Startup_Ack", "startup accepted (ACK_OK) or refused (Notnow, Start_Fail)", **ACK),',
        f'_msg("Startup_Ack", "startup accepted or refused", build="str?@{NEW_WIRE}", **ACK),',
    )
    patch(root / "gwc" / "module.py", 'note=f"{m.name} is already started")', 'note="already", build="2")')
    patch(root / "gwc" / "schema.py", f"SCHEMA_VERSION = {SCHEMA_VERSION}\n", f"SCHEMA_VERSION = {NEW_SCHEMA}\n")
    (root / "sql" / "096_upgrade_test.sql").write_text(
        "alter table lot_status add column if not exists upgrade_note text;\n"
        f"select schema_version_reached({NEW_SCHEMA}, {SCHEMA_VERSION}, 'lot_status.upgrade_note');\n"
    )
    return root


def new_env(cell: CellHarness, build: Path) -> dict[str, str]:
    return {**cell.env(), "PYTHONPATH": str(build)}


def run_new(cell: CellHarness, build: Path, *args: str, timeout: float = 60) -> str:
    result = subprocess.run(  # in the build's folder: `python -m` puts the working folder first on the path
        [sys.executable, "-m", "gwc", *args],
        env=new_env(cell, build),
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=build,
    )
    return ok(result)


@pytest.fixture
def upgrade_cell(xprocess: Any, tmp_path_factory: pytest.TempPathFactory, pg_cluster: Any) -> Iterator[Any]:
    import uuid

    from psycopg import sql

    name = f"gwc_t_{uuid.uuid4().hex[:12]}"
    with pg_cluster.admin() as conn:
        conn.execute(
            sql.SQL("create database {} template {}").format(sql.Identifier(name), sql.Identifier(pg_cluster.template))
        )
    cell = leased_cell(lambda **c: CellHarness(xprocess, tmp_path_factory.mktemp("upgrade"), pg_cluster.url(name), **c))
    old, new = Standbys(cell), Standbys(cell)
    try:
        cell_with_machines(cell, "wc1", "wc2", "cmm_wc")
        yield cell, old, new, second_build(tmp_path_factory.mktemp("build"))
    finally:
        stop_lot_scripts(cell)
        cell.close()
        old.close()
        new.close()
        with pg_cluster.admin() as conn:
            conn.execute(sql.SQL("drop database if exists {} with (force)").format(sql.Identifier(name)))


def start_standby(standbys: Standbys, name: str, build: Path | None) -> subprocess.Popen[bytes]:
    """A standby of this build (None) or of the second, started as an agent would."""
    if build is None:
        return standbys.start(name)
    cell = standbys.cell
    out = open(cell.cfg.log_dir / f"standby-{name}-new-{len(standbys.procs)}.out", "wb")  # noqa: SIM115
    env = {k: v for k, v in new_env(cell, build).items() if k != MARK}
    p = subprocess.Popen(
        [sys.executable, "-m", "gwc", "run", name],
        env=env,
        stdout=out,
        stderr=subprocess.STDOUT,
        start_new_session=True,
        cwd=build,
    )
    out.close()
    standbys.procs.append(p)
    standbys.names[p.pid] = name
    return p


def test_msched_and_the_lot_server_handed_over_to_a_new_build_while_lots_run(upgrade_cell: Any, tmp_path: Path) -> None:
    """The default suite's walk, while 2 lots run: a module of the new build refuses the old schema;
    the schema migrated; h2's standbys started on the new build; h1's active instances handed over."""
    rolling_upgrade(*upgrade_cell, tmp_path, full=False)


@pytest.mark.soak  # 90 s on the shared 2-core machine
def test_a_rolling_upgrade_while_lots_run_loses_no_lot_and_both_versions_talk(
    upgrade_cell: Any, tmp_path: Path
) -> None:
    """The whole walk: h2's standbys of the old build replaced, h1's handed over, h1's instances back
    as standbys of the new build, lots of both builds ordered, `gwc upgrade status` asked."""
    rolling_upgrade(*upgrade_cell, tmp_path, full=True)


def rolling_upgrade(cell: CellHarness, old: Standbys, new: Standbys, build: Path, tmp_path: Path, full: bool) -> None:
    record = tmp_path / "monitor.jsonl"
    monitor = subprocess.Popen(
        [sys.executable, "-m", "gwc", "monitor", "--json", "--members", "--record", str(record), "--duration", "150"],
        env=cell.env(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert monitor.stderr is not None and "monitoring bus" in monitor.stderr.readline()
        if full:  # h2: standbys of the old build
            for name in LEASED:
                start_standby(old, name, None)
            for name in LEASED:
                wait_for(lambda name=name: standing_by(cell, name, 1), 20, f"a standby {name}")
        else:  # a module of the new build refuses the schema before the migration, saying what to do
            early = start_standby(new, "msched", build)
            assert early.wait(30) == 3
            assert "apply this build's schema first" in cell.log_text("msched")
        entities = order(cell, "milled_pawn=3" if full else "milled_pawn=2")  # lots of the old build
        for e in entities:
            wait_state(cell, e, "waiting_import")
        ok(gwc(cell, "import", "--all"))
        wait_for(
            lambda: cell.query("select count(*) from machine_status where status in ('Setup', 'Running')")[0][0] > 0,
            30,
            "a machine at work",
        )
        began = time.time()
        # 1. The schema, with the new build, while everything runs: additive, so the old build runs on.
        run_new(cell, build, "db", "init")
        assert cell.query("select version, compatible_from from schema_version") == [(NEW_SCHEMA, SCHEMA_VERSION)]
        # 2. h2: its standbys replaced by the new build's (standing by: nothing is interrupted).
        said = {name: cell.log_text(name).count("standby: ") for name in LEASED}
        old.close()
        for name in LEASED:
            start_standby(new, name, build)
        for name in LEASED:
            wait_for(lambda name=name: standing_by(cell, name, said[name] + 1), 20, f"a new {name} standby")
        # 3. h1: the active instances handed over, standby first, while the lots run.
        epochs = {name: holder(cell, name)[0] for name in LEASED}
        handed = run_new(cell, build, "upgrade", "handover", *LEASED)
        for name in LEASED:
            assert f"{name}: handed over" in handed and holder(cell, name)[0] == epochs[name] + 1
            assert f"it speaks wire version {NEW_WIRE}" in handed, handed
        status = run_new(cell, build, "upgrade", "status", "--listen", "0.5")
        assert f"database: schema {NEW_SCHEMA}, runs builds of schema {SCHEMA_VERSION}..{NEW_SCHEMA}" in status
        new_line = next(line for line in status.splitlines() if line.startswith(f"wire {NEW_WIRE}: "))
        assert "ls" in new_line and "msched" in new_line and "wc:wc1" not in new_line, status
        assert f"the cell speaks wire version {wire.VERSION}" in status, status
        if full:
            # 4. h1's instances come back on the new build, as standbys.
            for name in LEASED:
                start_standby(new, name, build)
            # Lots of the new build ordered now talk to machines of the old.
            entities += order_new(cell, build, "milled_pawn=2")
            versions = json.loads(run_new(cell, build, "upgrade", "status", "--json", "--listen", "1"))
            assert versions["modules"]["msched"] == NEW_WIRE and versions["modules"]["wc:wc1"] == wire.VERSION
            assert versions["cell_speaks"] == wire.VERSION and versions["runs_here"]
        # A field the new build added is left out for the old: an old receiver would drop it as unknown.
        conv, answer = cell.bus.request("STARTUP", message("Startup_Request", module="msched"), to="msched")
        conv.end()
        assert answer.first.ack_code == AckCode.NOTNOW and "build" not in answer.first.fields
        import_export_all(cell, entities, timeout=120)
        ended = time.time()
        no_run_twice(cell, entities)
        run_new(cell, build, "check")
    finally:
        monitor.terminate()
        monitor.wait(10)
    both_talking(record, began, ended)


def order_new(cell: CellHarness, build: Path, *items: str) -> list[int]:
    made = json.loads(run_new(cell, build, "order", "new", "--customer", "NJIT", *items, "--json"))
    return [e for lot in made["lots"] for e in lot["entities"]]


def both_talking(record: Path, began: float, ended: float) -> None:
    """In the monitor's record: modules of both versions heard, and messages from each to the other
    while the upgrade ran, every one in the older version (the one every module reads)."""
    from datetime import datetime

    recs = [json.loads(line) for line in record.read_text().splitlines()]
    members = {(r["member"], r["speaks"]) for r in recs if "member" in r}
    assert {v for _, v in members} >= {wire.VERSION, NEW_WIRE}, members
    msgs = [r for r in recs if "message" in r and began <= datetime.fromisoformat(r["time"]).timestamp() <= ended]
    speaks = {r["from"]: r["speaks"] for r in msgs if r.get("speaks")}
    talk = {(speaks.get(r["from"]), speaks.get(r["to"])) for r in msgs if r["to"]}
    assert (NEW_WIRE, wire.VERSION) in talk and (wire.VERSION, NEW_WIRE) in talk, talk
    assert {r["wire"] for r in msgs} == {wire.VERSION}
    print(f"monitor: {len(msgs)} messages during the upgrade; members {sorted(members)}")
