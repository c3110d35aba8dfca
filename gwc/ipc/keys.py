"""The cell's keys: made, rotated, stored and loaded here, and nowhere else (docs/security.md).

Two files, both JSON, both 0600:

* the *cell key file* (`[bus] key_file`, default var/secrets/cell.key) holds the cell id and every
  key: the module keys, which the cell's modules and `gwc` commands sign with, and the lot keys.
  Every module loads it;
* the *lot key file* (`[bus] lot_key_file`, default var/secrets/lot.key) holds the cell id and the lot
  keys only. Lot scripts are user code: their bus (any bus named `lot:...`) loads this file, never
  the other, and receivers take lot-key traffic only for the conversation classes a lot entity
  starts or answers (gwc/ipc/catalogue.py, LOT_CLASSES).

Each key has a role (module or lot), an id (1, 2, ... per role), 32 random bytes, the time from
which senders use it (`send_from`) and, once rotated out, the time until which receivers still
accept it (`until`). `gwc key rotate` adds a key that senders take up a little after every module
has re-read the file (modules look at its mtime every heartbeat) and keeps the old one accepted for
the overlap, so a running cell changes keys without a refused datagram.
"""

from __future__ import annotations

import json
import os
import secrets
import stat
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from gwc.config import BusConfig
from gwc.errors import BusError

FORMAT = "gwc-cell-keys 1"
KEY_BYTES = 32  # 256-bit keys for keyed BLAKE2b
CELL_ID_BYTES = 8
ROLES = ("module", "lot")
TAKE_UP = 3.0  # s after a rotation before senders use the new key: every module has re-read the file by then
DEFAULT_OVERLAP = 60.0  # s the old key stays accepted after a rotation


@dataclass(frozen=True)
class Key:
    role: str  # module | lot
    id: int
    secret: bytes
    send_from: float = 0.0  # unix time from which senders use it
    until: float | None = None  # unix time after which receivers refuse it (None: no end)

    def accepted(self, now: float) -> bool:
        return self.until is None or now <= self.until


@dataclass(frozen=True)
class KeySet:
    """What one process holds: its cell's id and the keys of its file."""

    cell_id: bytes
    keys: tuple[Key, ...]

    def sending(self, role: str, now: float) -> Key | None:
        """The key a sender of `role` signs with now: the newest it may use."""
        usable = [k for k in self.keys if k.role == role and k.send_from <= now and k.accepted(now)]
        return max(usable, key=lambda k: k.id, default=None)

    def next_change(self, now: float) -> float:
        """When, after `now`, a key is taken up by senders or refused by receivers (inf: never)."""
        times = (t for k in self.keys for t in (k.send_from, k.until) if t is not None and t > now)
        return min(times, default=float("inf"))

    def find(self, role: str, key_id: int, now: float) -> Key | None:
        """The key a receiver checks a datagram signed with (role, key_id) against; None if not accepted."""
        for k in self.keys:
            if k.id == key_id and k.role == role:
                return k if k.accepted(now) else None
        return None


def key_files(cfg: BusConfig) -> tuple[Path, Path]:
    """(cell key file, lot key file) of a bus configuration."""
    if not cfg.key_file or not cfg.lot_key_file:
        raise BusError("no key files configured ([bus] key_file and lot_key_file): every bus needs the cell's key")
    return Path(cfg.key_file), Path(cfg.lot_key_file)


def role_of(name: str) -> str:
    """The key role of a bus member: lot entities (`lot:...`) hold the lot key, every other the module key."""
    return "lot" if name.startswith("lot:") else "module"


def _parse(path: Path, text: str) -> KeySet:
    try:
        doc = json.loads(text)
        if doc.get("format") != FORMAT:
            raise ValueError(f"format is not {FORMAT!r}")
        cell_id = bytes.fromhex(doc["cell_id"])
        if len(cell_id) != CELL_ID_BYTES:
            raise ValueError(f"cell_id must be {CELL_ID_BYTES} bytes")
        keys = []
        for k in doc["keys"]:
            secret = bytes.fromhex(k["key"])
            if k["role"] not in ROLES or len(secret) != KEY_BYTES or not 0 < int(k["id"]) < 2**16:
                raise ValueError(f"bad key entry (role, {KEY_BYTES}-byte key, id 1..65535): {k.get('id')}")
            until = k.get("until")
            keys.append(Key(k["role"], int(k["id"]), secret, float(k.get("send_from", 0)), until and float(until)))
    except (ValueError, KeyError, TypeError, AttributeError) as e:
        raise BusError(f"key file {path} is unreadable: {e}; make a new one with `gwc key new --force`") from None
    return KeySet(cell_id, tuple(keys))


def read(path: Path) -> KeySet:
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise BusError(f"no cell key at {path}: make one with `gwc key new` (or copy the cell's)") from None
    except OSError as e:
        raise BusError(f"cannot read the cell key at {path}: {e}") from None
    return _parse(path, text)


def load(cfg: BusConfig, role: str) -> tuple[Path, KeySet]:
    """The key file a bus member of `role` loads, and what it holds."""
    cell_file, lot_file = key_files(cfg)
    path = lot_file if role == "lot" else cell_file
    return path, read(path)


def _dump(keyset: KeySet, roles: tuple[str, ...]) -> str:
    return json.dumps(
        {
            "format": FORMAT,
            "cell_id": keyset.cell_id.hex(),
            "keys": [
                {"role": k.role, "id": k.id, "key": k.secret.hex(), "send_from": k.send_from, "until": k.until}
                for k in keyset.keys
                if k.role in roles
            ],
        },
        indent=1,
    )


def _write(path: Path, text: str) -> None:
    """Write atomically (a reader sees the old file or the new, never half of one): a new file 0600, a
    replaced one with the mode and group it had (lot.key made group-readable for lot scripts run as
    another user stays so), less any bit for others."""
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.unlink(missing_ok=True)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
    try:
        try:
            was = os.stat(path)
        except FileNotFoundError:
            pass
        else:
            if was.st_gid != os.getegid():
                try:
                    os.fchown(fd, -1, was.st_gid)
                except PermissionError:
                    raise BusError(
                        f"cannot keep {path}'s group (gid {was.st_gid}): run this as root or as a member of it"
                    ) from None
            os.fchmod(fd, stat.S_IMODE(was.st_mode) & 0o660)
        with os.fdopen(fd, "w") as f:
            f.write(text + "\n")
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def save(cfg: BusConfig, keyset: KeySet) -> None:
    cell_file, lot_file = key_files(cfg)
    _write(cell_file, _dump(keyset, ROLES))
    _write(lot_file, _dump(keyset, ("lot",)))


def new(cfg: BusConfig, force: bool = False) -> KeySet:
    """A new cell id and a new key of each role, written to both files."""
    cell_file, _ = key_files(cfg)
    if cell_file.exists() and not force:
        raise BusError(f"{cell_file} exists: `gwc key rotate` changes keys on a running cell (--force replaces it)")
    keyset = KeySet(secrets.token_bytes(CELL_ID_BYTES), tuple(Key(r, 1, secrets.token_bytes(KEY_BYTES)) for r in ROLES))
    save(cfg, keyset)
    return keyset


def ensure(cfg: BusConfig) -> bool:
    """Make the cell's keys if it has none (set-up); True if made."""
    if Path(key_files(cfg)[0]).exists():
        return False
    new(cfg)
    return True


def rotate(
    cfg: BusConfig, overlap: float = DEFAULT_OVERLAP, take_up: float = TAKE_UP, now: float | None = None
) -> KeySet:
    """A new key per role, used from `take_up` s on (time enough for every host to have the new file);
    the current ones accepted for `overlap` s more, older ones dropped."""
    if take_up < TAKE_UP or overlap <= take_up:
        raise BusError(
            f"take-up must be at least {TAKE_UP:.0f} s (modules re-read the file within it) and the overlap longer"
        )
    now = time.time() if now is None else now
    _, old = load(cfg, "module")
    keys: list[Key] = []
    for role in ROLES:
        current = old.sending(role, now)
        if current is not None:
            keys.append(Key(role, current.id, current.secret, current.send_from, now + overlap))
        next_id = max((k.id for k in old.keys if k.role == role), default=0) + 1
        keys.append(Key(role, next_id, secrets.token_bytes(KEY_BYTES), now + take_up))
    keyset = KeySet(old.cell_id, tuple(keys))
    save(cfg, keyset)
    return keyset


def describe(keyset: KeySet, now: float | None = None) -> list[dict[str, Any]]:
    """The keys without their secrets, for `gwc key show`."""
    now = time.time() if now is None else now
    return [
        {
            "role": k.role,
            "id": k.id,
            "sending": keyset.sending(k.role, now) == k,
            "send_from": k.send_from,
            "until": k.until,
        }
        for k in keyset.keys
    ]
