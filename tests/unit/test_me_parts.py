"""The part directory as Listing 9 moves it (gwc/me/parts.py): a tar both ways, a plain file still taken,
and a tar that reaches outside its folder refused whole."""

from __future__ import annotations

import io
import tarfile

import pytest

from gwc.me.parts import PartError, is_tar, part_tar, program_from


def tar_of(*members: tuple[str, bytes], link: tuple[str, str] | None = None) -> bytes:
    out = io.BytesIO()
    with tarfile.open(fileobj=out, mode="w", format=tarfile.GNU_FORMAT) as tar:
        for name, data in members:
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
        if link:
            info = tarfile.TarInfo(link[0])
            info.type, info.linkname = tarfile.SYMTYPE, link[1]
            tar.addfile(info)
    return out.getvalue()


def test_the_part_directory_goes_as_a_tar_and_comes_back_as_its_program() -> None:
    data = part_tar("pawn", b"MEASURE pawn\n")
    assert is_tar(data)
    with tarfile.open(fileobj=io.BytesIO(data)) as tar:
        assert tar.getnames() == ["pawn", "pawn/pawn"]
    assert program_from("pawn", data) == b"MEASURE pawn\n"
    assert program_from("pawn", b"MEASURE pawn\n") == b"MEASURE pawn\n"  # a plain file: the program itself
    assert not is_tar(b"# alum_chess_set v1\nHOME\n")


def test_a_listing9_tar_of_the_part_folder_gives_its_program() -> None:
    # tar -cvf /usr/avail/part/pawn/pawn.tar /usr/avail/part/pawn/* (GNU tar strips the leading /)
    listing9 = tar_of(("usr/avail/part/pawn/pawn", b"P\n"), ("usr/avail/part/pawn/RESULTS", b"ok\n"))
    assert program_from("pawn", listing9) == b"P\n"
    one_file = tar_of(("pawn/PROGRAM", b"Q\n"))
    assert program_from("pawn", one_file) == b"Q\n"
    with pytest.raises(PartError, match="no one program"):
        program_from("pawn", tar_of(("pawn/A", b"1"), ("pawn/B", b"2")))


@pytest.mark.parametrize("name", ["../../x", "/etc/x", "pawn/../../x", "pawn/../../../etc/x"])
def test_a_tar_member_outside_the_part_directory_refuses_the_whole_upload(name: str) -> None:
    with pytest.raises(PartError, match="outside the part directory"):
        program_from("pawn", tar_of(("pawn/pawn", b"P\n"), (name, b"owned\n")))


def test_links_out_of_the_part_directory_are_refused() -> None:
    with pytest.raises(PartError):
        program_from("pawn", tar_of(("pawn/pawn", b"P\n"), link=("pawn/evil", "/etc/passwd")))
