"""The seeded plan of a soak: which lots arrive when, and which fault strikes what, when.

Everything random about a soak is drawn here, up front, from one `random.Random(seed)`: the same
seed and options give the same plan, action for action, so a failing run can be replayed. The
cell's own timing (who answers first) is not under our control; the plan is.
"""

from __future__ import annotations

import random
from dataclasses import asdict, dataclass, field
from typing import Any

SERVERS = ("cas", "ers", "ms", "ls", "sls", "msched")
OP_TYPE = "dummy_op"
PRIORITIES = (10, 20, 30)

# What the chaos driver does, and how often, relative to the others.
ACTION_WEIGHTS = {
    "kill_wc": 3,  # kill -9 a machine's WC, restart it
    "kill_me": 3,  # kill -9 a machine's ME, restart it
    "kill_pair": 3,  # kill -9 a machine's WC and ME together, restart both
    "kill_server": 5,  # kill -9 MSCHED or a server, restart it (STARTUP)
    "machine_stop": 3,  # `gwc machine stop`, later `gwc machine start`
    "faults": 2,  # kill -9 a WC or server and restart it with the bus fault injector on, then heal it
    "kill_lot": 1,  # kill -9 a running lot script (the agent restarts it; without one the Lot Server reaps it)
}
FAULTS = {"drop": 0.05, "duplicate": 0.05, "reorder": 0.05}


@dataclass(frozen=True)
class LotSpec:
    """One lot of the stream: when it is ordered, which machines it may use, its priority."""

    index: int
    at: float  # seconds after the soak starts
    alternatives: list[list[str]]  # each alternative: the machines it needs (all of them)
    priority: int
    op_type: str = OP_TYPE


@dataclass(frozen=True)
class Action:
    """One fault: what, on which target, when, and how long until it is undone."""

    index: int
    at: float  # seconds after the soak starts (not before the previous action is undone)
    kind: str
    target: str  # a machine id, a server name, or "lot" (a random running lot script, chosen then)
    downtime: float  # seconds from the fault to its repair
    seed: int = 0  # for `faults`: the injector's own seed; for `kill_lot`: which running script

    def describe(self) -> str:
        return f"#{self.index} {self.kind} {self.target} for {self.downtime:.1f}s"


@dataclass(frozen=True)
class Plan:
    seed: int
    minutes: float
    machines: tuple[str, ...]
    lots: list[LotSpec] = field(default_factory=list)
    actions: list[Action] = field(default_factory=list)

    def header(self) -> dict[str, Any]:
        return {
            "seed": self.seed,
            "minutes": self.minutes,
            "machines": list(self.machines),
            "lots": len(self.lots),
            "actions": len(self.actions),
        }

    def as_dict(self) -> dict[str, Any]:
        return {**self.header(), "lots": [asdict(x) for x in self.lots], "actions": [asdict(a) for a in self.actions]}


def make_plan(
    seed: int,
    minutes: float,
    machines: tuple[str, ...],
    lot_every: float = 2.0,
    action_every: tuple[float, float] = (6.0, 14.0),
    warmup: float = 5.0,
) -> Plan:
    """The plan of a soak of `minutes`: lots about every `lot_every` s, a fault every `action_every` s."""
    rnd = random.Random(seed)
    duration = minutes * 60.0
    lots: list[LotSpec] = []
    t = 0.0
    while True:
        t += rnd.expovariate(1.0 / lot_every)
        if t >= duration:
            break
        if rnd.random() < 0.4 or len(machines) < 2:
            alternatives = [[rnd.choice(machines)]]
        else:
            alternatives = [[m] for m in rnd.sample(machines, rnd.randint(2, min(3, len(machines))))]
        lots.append(LotSpec(len(lots), round(t, 3), alternatives, rnd.choice(PRIORITIES)))
    actions: list[Action] = []
    servers = list(SERVERS)
    rnd.shuffle(servers)  # every server is killed once before any is killed twice
    kinds, weights = zip(*ACTION_WEIGHTS.items())
    t = warmup
    while True:
        t += rnd.uniform(*action_every)
        if t >= duration:
            break
        kind = rnd.choices(kinds, weights)[0]
        if kind == "kill_server":
            target = servers.pop(0) if servers else rnd.choice(SERVERS)
            downtime = rnd.uniform(0.2, 4.0)
        elif kind == "faults":
            target = rnd.choice([*SERVERS, *(f"wc:{m}" for m in machines)])
            downtime = rnd.uniform(5.0, 15.0)
        elif kind == "kill_lot":
            target = "lot"
            downtime = 0.0
        elif kind == "machine_stop":
            target = rnd.choice(machines)
            downtime = rnd.uniform(2.0, 10.0)
        else:
            target = rnd.choice(machines)
            downtime = rnd.uniform(0.2, 6.0)
        actions.append(Action(len(actions), round(t, 3), kind, target, round(downtime, 3), rnd.randrange(1 << 30)))
    return Plan(seed, minutes, tuple(machines), lots, actions)
