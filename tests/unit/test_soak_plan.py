"""The soak's plan: everything random comes from the seed, so a failing run can be replayed."""

from __future__ import annotations

import json
from pathlib import Path

from gwc.soak.driver import SoakOptions, action_sequence, plan_header, read_header
from gwc.soak.plan import ACTION_WEIGHTS, PRIORITIES, SERVERS, make_plan

MACHINES = tuple(f"wc{i}" for i in range(1, 7))


def test_same_seed_gives_the_same_plan_and_another_seed_another() -> None:
    a, b = make_plan(42, 10, MACHINES), make_plan(42, 10, MACHINES)
    assert a.as_dict() == b.as_dict()
    assert make_plan(43, 10, MACHINES).as_dict() != a.as_dict()


def test_a_ten_minute_plan_mixes_every_kind_of_lot_and_fault() -> None:
    plan = make_plan(7, 10, MACHINES)
    assert 200 < len(plan.lots) < 400  # a lot about every 2 s
    assert {len(x.alternatives) for x in plan.lots} == {1, 2, 3}  # single machine and alternatives
    assert {x.priority for x in plan.lots} == set(PRIORITIES)
    assert {a.kind for a in plan.actions} == set(ACTION_WEIGHTS)
    server_kills = [a.target for a in plan.actions if a.kind == "kill_server"]
    assert set(server_kills[: len(SERVERS)]) == set(SERVERS)  # each server dies before any dies twice
    times = [a.at for a in plan.actions]
    assert times == sorted(times) and all(t < 600 for t in times)


def test_recorded_header_and_action_sequence_read_back(tmp_path: Path) -> None:
    opts = SoakOptions(seed=5, minutes=1.0, var=tmp_path, kinds=("kill_wc",))
    log = tmp_path / "actions.jsonl"
    log.write_text(
        "\n".join(
            json.dumps(x)
            for x in [
                plan_header(opts, make_plan(5, 1.0, MACHINES)),
                {"event": "fault", "index": 0, "kind": "kill_wc", "target": "wc3", "t": 7.1, "detail": "killed"},
                {"event": "repair", "index": 0, "kind": "kill_wc", "target": "wc3", "t": 9.0, "detail": "restarted"},
            ]
        )
        + "\n"
    )
    head = read_header(log)
    assert (head["seed"], head["minutes"], head["machines"], head["kinds"]) == (5, 1.0, 6, ["kill_wc"])
    assert action_sequence(log) == [("fault", 0, "kill_wc", "wc3"), ("repair", 0, "kill_wc", "wc3")]
