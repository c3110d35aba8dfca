"""Sessions and the login's lockout, kept in the web module's memory (a restart of the module logs
everyone out and forgets the counts: docs/web.md).

A session is a random 256-bit token in a cookie (HttpOnly, Secure, SameSite=Strict) and a CSRF token
of its own that every action must send back in the X-CSRF-Token header; it ends after `idle` seconds
unused or `longest` seconds in all, at logout, or when its user is removed or changes role.
"""

from __future__ import annotations

import hmac
import secrets
import time
from collections import deque
from dataclasses import dataclass

from gwc.users import Person


@dataclass
class Session:
    token: str
    person: Person
    csrf: str
    made: float = 0.0
    used: float = 0.0


class Sessions:
    def __init__(self, idle: float, longest: float) -> None:
        self.idle = idle
        self.longest = longest
        self._by_token: dict[str, Session] = {}

    def open(self, person: Person) -> Session:
        now = time.monotonic()
        s = Session(secrets.token_urlsafe(32), person, secrets.token_urlsafe(32), now, now)
        self._by_token[s.token] = s
        return s

    def get(self, token: str | None) -> Session | None:
        """The live session of a cookie, its use noted; None for none, or one that has expired."""
        if not token:
            return None
        s = self._by_token.get(token)
        if s is None:
            return None
        now = time.monotonic()
        if now - s.used > self.idle or now - s.made > self.longest:
            del self._by_token[token]
            return None
        s.used = now
        return s

    def alive(self, token: str) -> bool:
        """Whether a session still lives, without counting this as its use (an open event stream
        must not keep an unattended page's session alive for ever)."""
        s = self._by_token.get(token)
        now = time.monotonic()
        return s is not None and now - s.used <= self.idle and now - s.made <= self.longest

    def close(self, token: str) -> None:
        self._by_token.pop(token, None)

    def close_user(self, name: str) -> None:
        for token in [t for t, s in self._by_token.items() if s.person.name == name]:
            del self._by_token[token]

    def __len__(self) -> int:
        return len(self._by_token)

    @staticmethod
    def csrf_ok(session: Session, given: str | None) -> bool:
        return bool(given) and hmac.compare_digest(session.csrf, given or "")


class Lockout:
    """Wrong passwords counted per user name and per address over `window` seconds: `after` of them
    lock logins for that name (and from that address) for `lock` seconds after the last, right
    password or not; each wrong one past that locks again."""

    def __init__(self, after: int, lock: float, window: float = 600.0) -> None:
        self.after = after
        self.lock = lock
        self.window = max(window, lock)
        self._fails: dict[str, deque[float]] = {}

    def _recent(self, key: str) -> deque[float]:
        q = self._fails.setdefault(key, deque())
        now = time.monotonic()
        while q and now - q[0] > self.window:
            q.popleft()
        return q

    def locked_for(self, user: str, address: str) -> float:
        """Seconds the login stays locked for this name or address (0: open)."""
        longest = 0.0
        for key in (f"user:{user}", f"addr:{address}"):
            q = self._recent(key)
            if len(q) >= self.after:
                longest = max(longest, self.lock - (time.monotonic() - q[-1]))
        return longest

    def failed(self, user: str, address: str) -> None:
        now = time.monotonic()
        for key in (f"user:{user}", f"addr:{address}"):
            self._recent(key).append(now)

    def succeeded(self, user: str) -> None:
        self._fails.pop(f"user:{user}", None)
