"""ME, the machine side of a machine interface (thesis 6.3): one process per machine, off the bus.

`gwc run me --machine ID` runs the ME of machine ID; its kind in etc/cell.toml picks the machine:
a dummy (gwc.me.dummy, the thesis's MEN) or the CMM over RS-232 (gwc.me.cmm, Listing 9's line
protocol). The ME talks only to its WC, over the machine's queue pair (gwc.ipc.mq).
"""

from __future__ import annotations

import importlib
import logging
import threading

from gwc.config import ME_KINDS, Config, MachineSpec
from gwc.errors import ConfigError
from gwc.me.machine import MachineSide

ME_ANSWER = 10.0  # longest an ME may take to acknowledge a request (not counting operator alarms)


def answer_deadline(spec: MachineSpec) -> float:
    """How long the WC waits for its ME's answer to one request: a CMM's exchange may take its serial
    timeouts (a resync, then the answer), and a Kermit transfer its own, before it is answered."""
    if spec.kind == "cmm":
        from gwc.me.cmm import exchange_deadline

        return exchange_deadline(spec)
    return ME_ANSWER


def make_machine(cfg: Config, machine_id: str, log: logging.Logger) -> MachineSide:
    """The machine side for this machine's kind (gwc.config.ME_KINDS), its module imported only here."""
    spec = cfg.machine(machine_id)
    if spec.kind not in ME_KINDS:
        raise ConfigError(f"machine {machine_id}: no ME for kind {spec.kind!r} (known: {', '.join(ME_KINDS)})")
    module, _, cls = ME_KINDS[spec.kind].partition(":")
    machine: MachineSide = getattr(importlib.import_module(module), cls)(cfg, spec, log)
    return machine


def main(cfg: Config, machine_id: str, log: logging.Logger, stop: threading.Event) -> int:
    """Run the ME of `machine_id` until `stop` is set (SIGTERM); returns the exit code."""
    return make_machine(cfg, machine_id, log).serve(stop)
