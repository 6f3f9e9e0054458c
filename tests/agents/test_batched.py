"""The batched simulator path equals the per-agent one, bit for bit.

``simulate(batched=True)`` fuses every regular LFRE / SW-LFRE agent's neighbour values in
one call per round (:func:`agents.simulate.fuse_batch`) around the estimators' own
``begin`` / ``finish`` halves; ``batched=False`` calls each agent's ``step``. The per-agent
round logic is the single source of truth, so the two must agree exactly.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agents.api import load_experiment
from agents.simulate import batch_groups, make_channel, make_nodes, simulate
from estimation.trimmed_mean import fuse, fuse_blocks

SCEN = Path(__file__).resolve().parents[2] / "scenarios"

CASES = [
    # LFRE, p = 0.32 drops, the cancellation adversary
    ("mitra_cells.toml", ("run.rounds=120", "expect=[]")),
    # SW-LFRE with delays, loss windows and forged stamps
    ("mitra_sw_lfre.toml", ("run.rounds=120", "expect=[]")),
    # the median rule (Remark 7) and the plain average (non-resilient baseline)
    ("mitra_cells.toml", ("run.rounds=60", 'estimator.rule="median"', "expect=[]")),
    ("mitra_nonresilient.toml", ("run.rounds=60", "expect=[]")),
    # a generated team: 16 cells, 64 agents, n = 320
    ("mitra_cells.toml", ("run.rounds=12", "plant.params.K=16", "expect=[]")),
]


@pytest.mark.parametrize("name,overrides", CASES, ids=[f"{c[0]}:{'/'.join(c[1])}" for c in CASES])
def test_batched_equals_per_agent(name: str, overrides: tuple[str, ...]) -> None:
    exp, _ = load_experiment(SCEN / name, overrides, None)
    groups = batch_groups(exp, make_nodes(exp, make_channel(exp)))
    assert groups, "the scenario must exercise the batched path"
    assert sum(len(g.agents) for g in groups) == exp.N - len(exp.byzantine)
    a = simulate(exp, keep_trajectories=True, batched=True)
    b = simulate(exp, keep_trajectories=True, batched=False)
    assert np.array_equal(a.estimates, b.estimates)
    assert a.links == b.links
    # and the run is not trivial: estimates move and differ between agents
    assert np.ptp(a.estimates[-1], axis=0).max() > 0 or np.abs(a.estimates[-1]).max() > 0


def _block(draw, width_max: int) -> np.ndarray | None:
    if draw(st.booleans()) and width_max > 0:
        return None
    F = draw(st.integers(1, 6))
    d = draw(st.integers(1, width_max))
    vals = draw(st.lists(st.floats(-1e6, 1e6, allow_nan=False), min_size=F * d, max_size=F * d))
    a = np.array(vals).reshape(F, d)
    mask = np.array(draw(st.lists(st.booleans(), min_size=F * d, max_size=F * d))).reshape(F, d)
    return np.where(mask, a, np.nan)


@settings(max_examples=60, deadline=None)
@given(st.data(), st.sampled_from(["trimmed", "median", "average"]), st.integers(0, 2))
def test_fuse_batch_row_results_do_not_depend_on_the_batch(data, fusion: str, f: int) -> None:
    blocks = [_block(data.draw, 12) for _ in range(data.draw(st.integers(1, 5)))]
    got = fuse_blocks(blocks, fusion=fusion, f=f)
    for blk, g in zip(blocks, got):
        if blk is None:
            assert g is None
        else:
            np.testing.assert_array_equal(g, fuse(blk, fusion=fusion, f=f))


def test_two_runs_of_one_experiment_are_identical() -> None:
    # a Byzantine strategy keeps state (its RNG): every run starts from a fresh copy
    exp, _ = load_experiment(SCEN / "mitra_sw_lfre.toml", ("run.rounds=60", "expect=[]"), None)
    a = simulate(exp, keep_trajectories=True)
    b = simulate(exp, keep_trajectories=True)
    assert np.array_equal(a.estimates, b.estimates)
