"""People's passwords: argon2id, salted and slow, so a copy of the users table gives no password away
cheaply. The parameters are OWASP's first choice for argon2id (19 MiB, 2 passes, 1 lane): 0.10 s a
try on this project's 2-core machine under a load of 32, where argon2-cffi's defaults (64 MiB,
3 passes, 4 lanes) took 1.18 s, which every login, and a password-guessing flood the lockout must
absorb, would pay. The parameters are kept in each hash, so
they may be raised later without invalidating the stored ones."""

from __future__ import annotations

from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError

_hasher = PasswordHasher(time_cost=2, memory_cost=19456, parallelism=1)
MIN_LENGTH = 8
# A hash to check against when no such user exists, so a wrong name costs what a wrong password does.
_DUMMY = _hasher.hash("gwc-no-such-user")


def hash_password(password: str) -> str:
    if len(password) < MIN_LENGTH:
        raise ValueError(f"a password needs {MIN_LENGTH} characters or more")
    return _hasher.hash(password)


def verify(stored: str | None, given: str) -> bool:
    """Whether `given` is the password `stored` is the hash of (None: no such user, same cost)."""
    try:
        return _hasher.verify(stored or _DUMMY, given) and stored is not None
    except (VerificationError, InvalidHashError):
        return False
