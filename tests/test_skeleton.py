"""The bare Zenoh skeleton of `rse bench run` reproduces the scenario's message pattern."""

from __future__ import annotations

from pathlib import Path

import pytest

from agents.api import load_experiment
from agents.net.skeleton import run_skeleton, sizes_for

ROOT = Path(__file__).resolve().parents[1]


def test_sizes_carry_the_adversarys_pattern() -> None:
    exp, _ = load_experiment(ROOT / "scenarios" / "mitra_cells.toml", ("run.rounds=10", "expect=[]"), None)
    sz = sizes_for(exp)
    (b,) = exp.byzantine  # agent 5, the cancellation attack
    outs = tuple(exp.agent_ids[j] for j in exp.out_neighbours(b))
    assert sz.addressed[b] == outs and len(outs) > 1
    assert sz.needed[b] and exp.agent_ids[b] not in sz.needed[b]
    assert all(not sz.addressed[i] and not sz.needed[i] and not sz.reads[i] for i in range(exp.N) if i != b)
    # it reads its receivers' addressed messages by sender, never its own (as the runtime's adversary)
    me = exp.agent_ids[b]
    assert sz.reads[b] and {j for _, j in sz.reads[b]} <= set(outs) and all(s != me for s, _ in sz.reads[b])
    assert {s for s, _ in sz.reads[b]} == set(sz.needed[b])
    # the encoded sizes are the runtime's: an estimate of n = 80 floats is at least 640 bytes
    assert sz.est >= 8 * exp.n


@pytest.mark.multiprocess
def test_skeleton_runs_with_an_omniscient_adversary() -> None:
    exp, _ = load_experiment(ROOT / "scenarios" / "mitra_cells.toml", ("run.rounds=10", "expect=[]"), None)
    res = run_skeleton(sizes_for(exp), rounds=30, timeout=50.0)
    assert res["rounds"] == 30 and res["rounds_per_s"] > 0


@pytest.mark.multiprocess
def test_minimal_skeleton_runs_the_team_without_plant_messages_or_monitor() -> None:
    exp, _ = load_experiment(ROOT / "scenarios" / "lee_kim_shim.toml", ("run.duration=1", "expect=[]"), None)
    res = run_skeleton(sizes_for(exp), rounds=40, timeout=50.0, minimal=True)
    assert res["rounds"] == 40 and res["rounds_per_s"] > 0
