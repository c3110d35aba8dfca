"""The part directory as Listing 9 moves it: a tar of `<part>/`, both ways over Kermit.

Listing 9's CMM side runs `kermit ilbr` then `tar -xvf /usr/avail/part/*.tar` after ` DOWNLD !`, and
`tar -cvf .../<part>.tar /usr/avail/part/<part>/*` then `kermit ilbs ... <part>.tar` after ` UPLD !`.
So the ME sends a part program as `<part>.tar` holding `<part>/<part>`, and takes back either such a
tar (the program is its member named `<part>`, or the one file of the directory `<part>/`) or, from a
device that sends the program alone, a plain file.

What comes from the device is not trusted (docs/security.md): the ME receives it under a name of
its own choosing, in a folder of its own (never where the far end names), and reads the tar in
memory, refusing it whole if any member names an absolute path or `..`, is a link or a device, or
if it is larger than MAX_TAR.
"""

from __future__ import annotations

import io
import tarfile
from pathlib import PurePosixPath

MAX_TAR = 4 * 1024 * 1024  # bytes: a part directory larger than this is refused


class PartError(ValueError):
    """A part directory the ME will not take (unsafe member, no program in it, too large)."""


def part_tar(part: str, program: bytes) -> bytes:
    """`<part>.tar` as Listing 9's CMM extracts it: the directory `<part>/` with the program `<part>/<part>`."""
    out = io.BytesIO()
    with tarfile.open(fileobj=out, mode="w", format=tarfile.USTAR_FORMAT) as tar:
        folder = tarfile.TarInfo(part)
        folder.type, folder.mode = tarfile.DIRTYPE, 0o755
        tar.addfile(folder)
        info = tarfile.TarInfo(f"{part}/{part}")
        info.size, info.mode = len(program), 0o644
        tar.addfile(info, io.BytesIO(program))
    return out.getvalue()


def is_tar(data: bytes) -> bool:
    """Does `data` hold a tar (its first header's checksum checks)?"""
    try:
        with tarfile.open(fileobj=io.BytesIO(data), mode="r:"):
            return True
    except tarfile.TarError:
        return False


def unsafe(name: str) -> bool:
    """A member name that would land outside the folder it is extracted in."""
    path = PurePosixPath(name)
    return name.startswith(("/", "\\")) or ".." in path.parts or ":" in (path.parts[0] if path.parts else "")


def program_from(part: str, data: bytes) -> bytes:
    """The part program in what a device sent back: a tar of the part directory, or the program alone.

    PartError (the whole upload refused) for an unsafe tar: a member with an absolute path or `..`,
    a link, a device or a FIFO; for a tar larger than MAX_TAR; for one with no program in it."""
    if not is_tar(data):
        return data
    if len(data) > MAX_TAR:
        raise PartError(f"{part}.tar is {len(data)} bytes, over {MAX_TAR}")
    files: dict[str, bytes] = {}
    with tarfile.open(fileobj=io.BytesIO(data), mode="r:") as tar:
        for m in tar.getmembers():
            if unsafe(m.name) or ((m.issym() or m.islnk()) and unsafe(m.linkname)):
                raise PartError(f"{part}.tar: member {m.name!r} names a path outside the part directory: refused")
            if m.isdir():
                continue
            if not m.isfile():
                raise PartError(f"{part}.tar: member {m.name!r} is not a file (a link or a device): refused")
            f = tar.extractfile(m)
            files[m.name] = f.read() if f is not None else b""
    named = [n for n in files if PurePosixPath(n).name == part]
    in_dir = [n for n in files if PurePosixPath(n).parent.name == part]
    for choice in (named, in_dir, list(files)):
        if len(choice) == 1:
            return files[choice[0]]
    raise PartError(f"{part}.tar holds no one program of {part}: {', '.join(sorted(files)) or 'nothing'}")
