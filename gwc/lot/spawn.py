"""Starting lot script processes: by the host's agent when one runs, else detached. Apart from
gwc/lot/run.py (which runs a script, and so imports the entity) so that the entity's own steps that
start scripts (start_child, divide: gwc/lot/holdings.py) import no module that imports them back."""

from __future__ import annotations

from gwc.agent import control as agent_control
from gwc.cell import lot_proc, spawn
from gwc.config import Config


def spawn_lot_script(cfg: Config, entity_id: int) -> int | None:
    """Start the entity's lot script process with a pid file (so `gwc stop` stops it too): by this host's
    agent when one runs, which restarts it if it is killed (docs/reliability.md) and queues it while the
    most scripts it runs at once are running (None: queued, gwc/lot/admission.py); else detached."""
    return spawn_lot_scripts(cfg, [entity_id])[entity_id]


def spawn_lot_scripts(cfg: Config, entities: list[int]) -> dict[int, int | None]:
    """spawn_lot_script for many entities in one call to the agent: entity -> pid, None if queued."""
    try:
        answer = agent_control.call(cfg, "lots", entities=entities, timeout=30.0)
    except agent_control.NoAgent:
        return {e: spawn(cfg, lot_proc(e)) for e in entities}
    pids = answer["pids"]
    return {e: None if pids[str(e)] is None else int(pids[str(e)]) for e in entities}
