"""Hosts on one machine: network namespaces joined by a bridge, so a cell can be spread over several
"hosts" for its tests and benchmarks (tests/e2e/test_hosts.py, `gwc bench bus --hosts`).

Each host is a namespace with one interface, eth0, on 10.<n>.0.<i>/24, a veth whose other end sits on
a bridge in a namespace of its own. Putting the bridge in a namespace too means one `ip netns del`
per namespace removes everything (links and all), and the machine's own network is never touched.
Multicast crosses the bridge (snooping off, so no IGMP querier is needed), and each host routes
224.0.0.0/4 out of eth0, so the cell's bus works between hosts as on a plant LAN.

Processes run in a host through `ip netns exec`. Only the network is separate: the file system and
the POSIX queue namespace are shared, so each host gets a var/ of its own to keep the no-shared-files
promise honest.
"""

from __future__ import annotations

import contextlib
import os
import random
import shutil
import subprocess
from collections.abc import Sequence
from dataclasses import dataclass

PREFIX = "gwcn"  # every namespace and link made here starts with this, so leftovers can be found


def unavailable() -> str | None:
    """Why hosts cannot be built here (None when they can): they need root and iproute2."""
    if os.geteuid() != 0:
        return "namespace hosts need root (network namespaces)"
    if shutil.which("ip") is None:
        return "namespace hosts need iproute2's `ip`"
    probe = f"{PREFIX}probe{os.getpid()}"
    made = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
    if made.returncode != 0:
        return f"cannot make a network namespace here: {made.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", probe], capture_output=True)
    return None


def ip(*args: str, ns: str | None = None) -> None:
    """Run one `ip` command (in namespace ns), failing loudly with its message."""
    argv = ["ip", *(["-n", ns] if ns else []), *args]
    r = subprocess.run(argv, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)}: {r.stderr.strip()}")


@dataclass(frozen=True)
class Host:
    name: str  # h1, h2, ...
    netns: str
    address: str
    link: str  # the veth end on the bridge: cut it to take the host off the network

    def argv(self, argv: Sequence[str]) -> list[str]:
        """argv run inside this host."""
        return ["ip", "netns", "exec", self.netns, *argv]


class Hosts:
    """N hosts on one bridge. Use as a context manager; everything is removed on exit."""

    def __init__(self, count: int) -> None:
        self.tag = f"{os.getpid() % 10000}{random.randrange(100):02d}"
        self.subnet = f"10.{random.randrange(64, 250)}.{random.randrange(1, 250)}"
        self.bridge_ns = f"{PREFIX}{self.tag}br"
        self.hosts = [
            Host(f"h{i}", f"{PREFIX}{self.tag}h{i}", f"{self.subnet}.{i}", f"{PREFIX}{self.tag}v{i}")
            for i in range(1, count + 1)
        ]

    def __enter__(self) -> Hosts:
        try:
            self._build()
        except BaseException:
            self.remove()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.remove()

    def __getitem__(self, name: str) -> Host:
        return next(h for h in self.hosts if h.name == name)

    def _build(self) -> None:
        ip("netns", "add", self.bridge_ns)
        ip("link", "add", "br0", "type", "bridge", "mcast_snooping", "0", ns=self.bridge_ns)
        ip("link", "set", "br0", "up", ns=self.bridge_ns)
        for h in self.hosts:
            ip("netns", "add", h.netns)
            ip("link", "add", h.link, "netns", self.bridge_ns, "type", "veth", "peer", "name", "eth0", "netns", h.netns)
            ip("link", "set", h.link, "master", "br0", "up", ns=self.bridge_ns)
            ip("addr", "add", f"{h.address}/24", "dev", "eth0", ns=h.netns)
            ip("link", "set", "eth0", "up", ns=h.netns)
            ip("link", "set", "lo", "up", ns=h.netns)
            ip("route", "add", "224.0.0.0/4", "dev", "eth0", ns=h.netns)

    def cut(self, name: str) -> None:
        """Unplug a host's cable (its link on the bridge goes down)."""
        ip("link", "set", self[name].link, "down", ns=self.bridge_ns)

    def mend(self, name: str) -> None:
        ip("link", "set", self[name].link, "up", ns=self.bridge_ns)

    def remove(self) -> None:
        """Kill what runs in the hosts and delete every namespace (their links go with them)."""
        for ns in [h.netns for h in self.hosts] + [self.bridge_ns]:
            pids = subprocess.run(["ip", "netns", "pids", ns], capture_output=True, text=True).stdout.split()
            for pid in pids:
                with contextlib.suppress(ProcessLookupError, ValueError):
                    os.kill(int(pid), 9)
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def leftovers(tag: str = "") -> list[str]:
    """Namespaces of such hosts still present (a leak check for tests); with `tag` (Hosts.tag), only those
    of that set of hosts: others may be building theirs on the same machine meanwhile."""
    out = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    return [line.split()[0] for line in out.splitlines() if line.startswith(PREFIX + tag)]
