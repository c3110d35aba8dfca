"""`gwc bench cell --freezes N`: a running machine's WC frozen, and how many runs the cell did twice.

Beside gwc/bench/cell.py's death trials (a kill -9 of the machine pair, which the host's agent
announces at once): here the WC of the machine a lot runs on is stopped (SIGSTOP) for `freeze`
seconds, longer than its liveness, while its ME goes on with the run. The Machine Server marks the
machine Shutdown, unheard; the lot holds the run in doubt rather than run it again; the WC wakes,
stores the run; the lot uses it. A run done twice is an entity with runs on two machines (its
traveller's steps with results, and MACHINE_RUN_OUTCOME rows of its runs): the bar is 0.
"""

from __future__ import annotations

import os
import signal
import time
from typing import TYPE_CHECKING, Any

from gwc.cell import read_pid
from gwc.errors import GwcError
from gwc.lot.entity import read_traveller

if TYPE_CHECKING:
    from gwc.bench.cell import CellBench

FREEZE = 8.0  # seconds a WC is stopped: longer than the 3 s liveness of the bench's machines


def freeze_trials(bench: CellBench, trials: int, freeze: float = FREEZE) -> dict[str, Any]:
    """Freeze the WC of a running lot's machine `trials` times; the runs done twice, and how each ended."""
    assert bench.conn is not None
    bench.say(f"{trials} freeze trials: SIGSTOP the WC of the machine a lot runs on for {freeze:g}s")
    twice = 0
    ended: dict[str, int] = {}
    for k in range(trials):
        entity, victim, deadline, decided = bench.running_lot(f"freeze trial {k + 1}")
        pid = read_pid(bench.cell.cfg, f"wc:{victim}").pid
        if pid is None:
            raise GwcError(f"freeze trial {k + 1}: wc:{victim} has no process")
        os.kill(pid, signal.SIGSTOP)
        try:
            time.sleep(freeze)
        finally:
            os.kill(pid, signal.SIGCONT)
        while (state := bench.operator(decided, [entity]).get(entity)) not in ("exported", "failed"):
            if deadline.expired:
                raise GwcError(f"freeze trial {k + 1}: entity {entity} did not finish")
            time.sleep(0.05)
        runs = _runs_done(bench, entity)
        twice += len(runs) > 1
        ended[state] = ended.get(state, 0) + 1
        bench.say(f"  trial {k + 1}: wc:{victim} frozen {freeze:g}s; lot {state}, runs done: {runs}")
        bench.machine_up(victim)
    return {"trials": trials, "freeze_s": freeze, "runs_done_twice": twice, "lots": ended}


def _runs_done(bench: CellBench, entity: int) -> list[str]:
    """'machine:run' of every run the entity's operation was done by (results stored, or counted by the lot)."""
    assert bench.conn is not None
    steps = (read_traveller(bench.cell.cfg, entity) or {}).get("steps", [])
    run_ids = [int(s["machine_run_id"]) for s in steps]
    rows = bench.conn.execute(
        "SELECT machine_id, machine_run_id FROM machine_run_outcome WHERE machine_run_id = ANY(%s) "
        "AND ack_code = 'ACK_OK' ORDER BY ended_at",
        (run_ids,),
    ).fetchall()
    return [f"{m}:{r}" for m, r in rows]
