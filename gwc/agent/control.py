"""The agent's control socket, and the client `gwc start|stop|status|restart` use.

One request per connection: a JSON line `{"cmd": ..., ...}`; the agent answers with any number of
`{"say": text}` lines (progress, for a person) and ends with `{"done": true, "ok": bool, ...}`.
The socket is in Linux's abstract namespace, named after the cell's var/ (as its queues are), so it
needs no file, cannot be left behind, and is private to the host (a network namespace) it runs on.
An abstract socket has no file mode: any local user can connect. So the agent asks the kernel who
connected (SO_PEERCRED) and takes commands only from the cell's user (its own) and root; every
command is logged with the asker's uid and pid (docs/security.md, Local users).
"""

from __future__ import annotations

import json
import os
import socket
import struct
from collections.abc import Callable
from typing import Any, NamedTuple

from gwc.config import Config
from gwc.errors import ModuleError

CALL_TIMEOUT = 120.0  # a `start` waits for every module to come up
READY_FD = "GWC_READY_FD"  # the pipe an off-bus module writes to once it serves (set by the agent)


class NoAgent(ModuleError):
    """No agent answers on this host for this cell."""


class Peer(NamedTuple):
    """Who is at the other end of a unix socket, as the kernel tells (SO_PEERCRED)."""

    pid: int
    uid: int
    gid: int

    @property
    def allowed(self) -> bool:
        """The cell's user (the agent's own) and root may command the agent; nobody else."""
        return self.uid in (0, os.geteuid())


def peer_of(sock: socket.socket) -> Peer:
    creds = sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
    return Peer(*struct.unpack("3i", creds))


def address(cfg: Config) -> str:
    """The agent's abstract socket name: one per cell (var/) per host."""
    return "\0" + cfg.ipc_prefix.lstrip("/") + ".agent"


def call(
    cfg: Config, cmd: str, say: Callable[[str], None] = lambda s: None, timeout: float = CALL_TIMEOUT, **args: Any
) -> dict[str, Any]:
    """Send one command to this host's agent and return its final answer; progress lines go to `say`.

    Raises NoAgent if none runs, ModuleError if the agent answers that the command failed."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.settimeout(timeout)
    try:
        try:
            sock.connect(address(cfg))
        except (ConnectionRefusedError, FileNotFoundError):
            raise NoAgent(f"no agent runs for {cfg.var} on this host (start the cell with `gwc start`)") from None
        sock.sendall(json.dumps({"cmd": cmd, **args}).encode() + b"\n")
        with sock.makefile("r", encoding="utf-8") as lines:
            for line in lines:
                answer = json.loads(line)
                if "say" in answer:
                    say(str(answer["say"]))
                if answer.get("done"):
                    if not answer.get("ok"):
                        raise ModuleError(str(answer.get("error") or f"agent: {cmd} failed"))
                    return dict(answer)
    except TimeoutError:
        raise ModuleError(f"the agent did not finish `{cmd}` within {timeout:.0f}s") from None
    except OSError as e:
        raise ModuleError(f"agent: {cmd}: {e}") from e
    finally:
        sock.close()
    raise ModuleError(f"the agent closed the connection before finishing `{cmd}`")


def running(cfg: Config) -> bool:
    """Whether an agent answers for this cell on this host."""
    try:
        call(cfg, "ping", timeout=5.0)
    except ModuleError:
        return False
    return True


def notify_ready() -> None:
    """Tell the agent that started this process that it now serves (the ME and the CMM simulator are
    off the bus, so this is their proof of readiness). A no-op when no agent started us."""
    fd = os.environ.pop(READY_FD, None)
    if fd is None:
        return
    try:
        os.write(int(fd), b"R")
        os.close(int(fd))
    except (OSError, ValueError):
        pass  # the agent went away or the variable is not ours: nothing to tell
