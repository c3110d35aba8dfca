"""Fixtures every test may use.

Database: `pg_cluster` starts ONE embedded PostgreSQL cluster for the whole session (under
/var/tmp, which the postgres OS user can traverse when we are root) with a template database
holding the schema and seed; `database_url` clones a fresh database from it for each test.
`make_config` writes a cell.toml for a test.

Every test fails if it leaves a process, POSIX queue, socket or database cluster behind (tests/leaks.py),
and every test under tests/e2e/ is marked `e2e`, so `bin/test -m "not e2e"` is the fast inner loop.
"""

from __future__ import annotations

import contextlib
import dataclasses
import shutil
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import psycopg
import pytest
from psycopg import sql

from gwc import db
from gwc.config import Config
from gwc.soak.private_config import write_config
from tests.leaks import kill_on_termination, leak_check, unmarked

TEMPLATE_DB = "gwc_template"
# Test clusters trade durability for speed: a crashed test cluster is thrown away anyway.
TEST_PG_SETTINGS = {"fsync": False, "synchronous_commit": False, "full_page_writes": False}


# ----------------------------------------------------------------------------- configuration


def make_config(tmp_dir: Path, database_url: str | None, **sections: Any) -> Config:
    """Write tmp_dir/etc/cell.toml (state in tmp_dir/var) and load it.

    Keyword arguments are cell.toml's top-level keys: a dict is a [section] (merged over the
    defaults), a list is an array of tables, e.g.
    make_config(d, url, cell={"policy": "priority"}, machine=[{"id": "wc1", "kind": "dummy"}],
                database={"settings": {"fsync": False}}).
    """
    tmp_dir = Path(tmp_dir)
    doc: dict[str, Any] = {
        "cell": {"name": "test", "var": str(tmp_dir / "var")},
        "database": {"url": database_url or ""},
        "log": {"level": "note"},
    }
    for key, value in sections.items():
        doc[key] = {**doc[key], **value} if isinstance(value, dict) and key in doc else value
    return write_config(tmp_dir / "etc" / "cell.toml", doc)


# ----------------------------------------------------------------------------- database


@dataclasses.dataclass(frozen=True)
class PgCluster:
    """The session's embedded cluster: `cfg` drives gwc.db; `url(name)` reaches any of its databases."""

    cfg: Config
    template: str = TEMPLATE_DB

    def url(self, dbname: str) -> str:
        return db.database_url(self.cfg).replace(f"@/{db.DB_NAME}?", f"@/{dbname}?", 1)

    def admin(self) -> psycopg.Connection[Any]:
        """An autocommit superuser connection to the maintenance database (CREATE/DROP DATABASE)."""
        return psycopg.connect(self.url("postgres"), autocommit=True)


@pytest.fixture(scope="session")
def pg_cluster() -> Iterator[PgCluster]:
    """One embedded cluster for the session, with a template database already initialised."""
    base = Path(tempfile.mkdtemp(prefix="gwc-pg-", dir="/var/tmp"))
    base.chmod(0o755)
    cfg = dataclasses.replace(make_config(base, None, database={"settings": TEST_PG_SETTINGS}), database_url=None)
    try:
        with unmarked():  # the session's cluster outlives the test that happens to start it
            db.cluster_start(cfg)
        cluster = PgCluster(cfg)
        with cluster.admin() as conn:
            conn.execute(sql.SQL("create database {}").format(sql.Identifier(TEMPLATE_DB)))
        db.init_schema(dataclasses.replace(cfg, database_url=cluster.url(TEMPLATE_DB)))
        yield cluster
    finally:
        with contextlib.suppress(Exception):
            db.cluster_stop(cfg)
        shutil.rmtree(base, ignore_errors=True)


@pytest.fixture
def database_url(pg_cluster: PgCluster) -> Iterator[str]:
    """A fresh database with schema and seed, cloned for this test and dropped after it (use as GWC_DATABASE_URL)."""
    name = f"gwc_t_{uuid.uuid4().hex[:12]}"
    with pg_cluster.admin() as conn:
        conn.execute(
            sql.SQL("create database {} template {}").format(sql.Identifier(name), sql.Identifier(pg_cluster.template))
        )
    yield pg_cluster.url(name)
    with pg_cluster.admin() as conn:
        conn.execute(sql.SQL("drop database if exists {} with (force)").format(sql.Identifier(name)))


@pytest.fixture
def cell_config(tmp_path: Path, database_url: str) -> Config:
    """A Config for this test, on its own fresh database (external URL, so nothing to start)."""
    return make_config(tmp_path, database_url)


@pytest.fixture
def db_conn(database_url: str) -> Iterator[psycopg.Connection[Any]]:
    """A superuser connection (autocommit off) to this test's fresh database, closed after it."""
    with psycopg.connect(database_url) as conn:
        yield conn


# ----------------------------------------------------------------------------- what a test leaves behind


def pytest_configure(config: pytest.Config) -> None:
    if not hasattr(config, "workerinput"):  # the controller (or a run without xdist)
        kill_on_termination()


@pytest.fixture(autouse=True)
def no_leaks(tmp_path: Path) -> Iterator[None]:
    """Fail the test if it leaves a process, POSIX queue, socket or database cluster behind."""
    with leak_check(tmp_path):
        yield


# ----------------------------------------------------------------------------- markers: e2e, the long soak

E2E_DIR = Path(__file__).parent / "e2e"


@pytest.hookimpl(tryfirst=True)  # before -m deselects
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Every test under tests/e2e/ is `e2e`; tests marked `soak` (the long chaos soak) run only when asked
    for: `bin/test -m soak`."""
    for item in items:
        if E2E_DIR in item.path.parents:
            item.add_marker(pytest.mark.e2e)
    if "soak" in (config.getoption("markexpr") or ""):
        return
    skip = pytest.mark.skip(reason="the long chaos soak runs apart: bin/test -m soak")
    for item in items:
        if item.get_closest_marker("soak") is not None:
            item.add_marker(skip)
