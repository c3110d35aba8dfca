"""The installable package: sql/ and etc/ ship inside it, and `pip install .` into a new virtualenv, then
`gwc demo` in an empty folder, exits 0 with its state in the user's state folder, not in the package.

The wheel's contents are checked in the ordinary run (a few seconds); the whole install and demo take a
few minutes (pip resolves and installs the dependencies, the demo runs section 7), so that test is
`soak`. It runs the real `gwc demo`, default configuration and all, in a network namespace of its own,
so its fixed bus port and group meet nobody else's.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import zipfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from gwc.config import PROJECT_ROOT
from tests.leaks import MARK

SHIPPED = [
    "gwc/data/sql/010_tables.sql",
    "gwc/data/sql/900_seed.sql",
    "gwc/data/etc/cell.toml",
    "gwc/data/etc/demo.toml",
]


@pytest.fixture
def scratch() -> Iterator[Path]:
    """An empty folder outside the checkout that the postgres user can traverse (the demo's cluster)."""
    where = Path(tempfile.mkdtemp(prefix="gwc-install-", dir="/var/tmp"))
    where.chmod(0o755)
    try:
        yield where
    finally:
        shutil.rmtree(where, ignore_errors=True)


def test_the_wheel_ships_sql_and_the_default_configuration(scratch: Path) -> None:
    build = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(scratch), "."],
        cwd=PROJECT_ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert build.returncode == 0, build.stdout + build.stderr
    (wheel,) = scratch.glob("gwc-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    missing = [n for n in SHIPPED if n not in names]
    assert not missing, f"not in the wheel: {missing}"
    assert not any(n.startswith(("var/", "gwc/data/var")) for n in names), "state shipped in the wheel"


@pytest.mark.soak
def test_pip_install_into_a_new_virtualenv_then_gwc_demo_exits_0(scratch: Path) -> None:
    venv = scratch / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    install = subprocess.run(
        [str(venv / "bin" / "pip"), "install", "-q", str(PROJECT_ROOT)], capture_output=True, text=True, timeout=600
    )
    assert install.returncode == 0, install.stdout[-3000:] + install.stderr[-3000:]
    empty = scratch / "empty"
    empty.mkdir()
    state = scratch / "state"
    env = {k: v for k, v in os.environ.items() if k == MARK or not k.startswith(("GWC_", "PYTHON", "VIRTUAL_ENV"))}
    env.update(XDG_STATE_HOME=str(state), HOME=str(scratch), PATH=f"{venv / 'bin'}:{env.get('PATH', '')}")
    demo = subprocess.run(
        ["unshare", "--net", "sh", "-c", "ip link set lo up && exec gwc demo"],
        cwd=empty,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    out = demo.stdout + demo.stderr
    assert demo.returncode == 0, out[-6000:]
    assert "demonstration succeeded" in out
    assert (state / "gwc" / "var" / "demo" / "log").is_dir(), "the demo's state is not in the user's state folder"
    site = next((venv / "lib").glob("python*/site-packages"))
    assert not (site / "var").exists() and not (site / "gwc" / "data" / "var").exists(), (
        "state written into the package"
    )
    assert not list(empty.iterdir()), "the demo wrote into the folder it was run from"
