"""The CMM line as Listing 9 has it, against an independent Listing 9 CMM (tests/e2e/listing9_cmm.py, no
gwc code) on a pty at 8E1: the part directory by Kermit as a tar both ways, a measured chess lot, an
upload stored as the recipe; and a hostile far end, which never chooses where an upload lands."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from gwc.ipc.catalogue import message
from gwc.ipc.codes import AckCode
from tests.e2e.lotkit import cell_with_machines, import_export_all, order, state

pytestmark = pytest.mark.skipif(shutil.which("gkermit") is None, reason="gkermit is not installed (bin/setup)")
DEVICE = Path(__file__).with_name("listing9_cmm.py")


def upload(cell: Any) -> Any:
    conv, batch = cell.bus.request(
        "UPLD_ME", message("Upload_Me", machine_id="cmm_wc", recipe_id="alum_chess_set"), to="wc:cmm_wc", timeout=40
    )
    conv.end()
    return batch.first


def test_a_listing9_cmm_at_8e1_takes_and_gives_its_part_directory_by_kermit_tar_and_a_hostile_one_lands_nothing(
    lot_cell: Any, tmp_path: Path
) -> None:
    master, slave = os.openpty()
    folder = tmp_path / "usr-avail-part"
    device_log = (tmp_path / "listing9.log").open("w")
    device = subprocess.Popen(
        [sys.executable, str(DEVICE), str(master), os.ttyname(slave), str(folder)],
        pass_fds=(master,),
        stdout=device_log,
        stderr=subprocess.STDOUT,
    )
    try:
        spec = {
            "id": "cmm_wc",
            "kind": "cmm",
            "serial": {"port": os.ttyname(slave), "baudrate": 9600, "bytesize": 8, "parity": "E", "timeout": 5.0},
            "transfer": "kermit",
            "run_timeout": 20.0,
        }
        cell = cell_with_machines(lot_cell(machines=[spec]), "cmm_wc")
        said = lambda: (tmp_path / "listing9.log").read_text()

        # A measured lot: SETUP_RUN sends alum_chess_set.tar by Kermit, the device untars it, measures PASS.
        (lot,) = order(cell, "alum_chess_set=1")
        import_export_all(cell, [lot], timeout=90)
        assert state(cell, lot)[0] == "exported" and (state(cell, lot)[1] or "").startswith("PASS"), state(cell, lot)
        program = folder / "alum_chess_set" / "alum_chess_set"
        approved = cell.query("SELECT content FROM recipe_versions WHERE recipe_id = 'alum_chess_set' AND approved")
        assert program.read_bytes() == bytes(approved[0][0]), said()
        assert "untarred ['alum_chess_set.tar']" in said(), said()
        assert cell.log_has("me:cmm_wc", f"serial line to the CMM open: {os.ttyname(slave)} at 9600 8E1")

        # The part program edited at the CMM comes back as alum_chess_set.tar and is stored as the recipe.
        program.write_text(program.read_text() + "TOLERANCE 0.04 mm\n")
        up = upload(cell)
        assert up.ack_code == AckCode.ACK_OK and up.version == 2, up
        stored = cell.query("SELECT content FROM recipe_versions WHERE recipe_id = 'alum_chess_set' AND version = 2")
        assert bytes(stored[0][0]) == program.read_bytes()
        assert "upload alum_chess_set.tar (the part directory): kermit 0" in said()

        # A hostile far end: the name it sends is not where the file lands; a tar reaching out is refused.
        me = cell.cfg.var / "me" / "cmm_wc"
        inbox = me / "kermit-in"
        outside = [inbox.parent.parent / "x", Path("/etc/x"), tmp_path / "x"]
        before = {p: p.exists() for p in outside}
        for hostile in ("name:../../x", "name:/etc/x"):
            (folder / "mode").write_text(hostile)
            up = upload(cell)
            assert up.ack_code == AckCode.ACK_OK, (hostile, up)  # the program itself, under the ME's name
            assert sorted(p.name for p in inbox.iterdir()) == ["upload"], hostile
            assert {p: p.exists() for p in outside} == before, hostile
        for hostile in ("tar:../../x", "tar:/etc/x"):
            (folder / "mode").write_text(hostile)
            up = upload(cell)
            assert up.ack_code == AckCode.REC_INVAL and "outside the part directory" in (up.note or ""), up
            assert {p: p.exists() for p in outside} == before, hostile
        assert cell.log_has("me:cmm_wc", "names a path outside the part directory: refused")
        versions = cell.query("SELECT count(*) FROM recipe_versions WHERE recipe_id = 'alum_chess_set'")[0][0]
        assert versions == 2  # the hostile program equals v2: nothing new stored, nothing of the tars
    finally:
        device.kill()
        device.wait()
        device_log.close()
        os.close(master)
        os.close(slave)
