"""Estimator diagnostics and attack flags reach the networked monitor exactly as in the
simulator (the networked roles over the in-memory bus: the protocol of `rse run`)."""

import asyncio

import pytest

from agents.api import load_experiment
from agents.net.roles import RunConfig, run_team_in_memory
from agents.simulate import simulate
from agents.summary import summarise
from tests.conftest import SCENARIOS

BIAS = 'attacks=[{target = "sensor", sensors = [3, 6], kind = "trajectory", x0_attack = [-2.0, 1.5, -1.0, 2.5]}, ' \
       '{target = "sensor", sensors = [6], kind = "constant", start = 150, value = 1.0}]'


def both(name, overrides, batched=True):
    exp, _ = load_experiment(SCENARIOS / name, overrides, None)
    ref = simulate(exp, batched=batched)
    ref_summary = summarise(exp, ref.monitor, ref.regular, ref.links)
    exp, _ = load_experiment(SCENARIOS / name, overrides, None)
    res = asyncio.run(asyncio.wait_for(run_team_in_memory(exp, RunConfig(deadline=30.0)), 600))
    return ref_summary, res.summary


def test_mao_tabuada_flags_under_the_networked_roles():
    ref, net = both("mao_tabuada.toml", ("run.rounds=170", "expect=[]", BIAS))
    assert ref["detected_attacks"]["agents"] == [6]
    assert net["detected_attacks"] == ref["detected_attacks"]


@pytest.mark.needs("cvxpy", "the H-infinity LMIs")
def test_ugrinovskii_flags_under_the_networked_roles():
    # the networked roles step each agent alone: bit-identical to the per-agent simulator
    # (the batched one agrees within 1e-12, docs/simulator.md; tests/agents/test_batched_algorithms.py)
    ref, net = both("ugrinovskii_biasing.toml", ("run.duration=5.0", "expect=[]"), batched=False)
    assert ref["detected_attacks"]["agents"] == [2]
    assert net["detected_attacks"] == ref["detected_attacks"]
    assert net["diagnostics"] == ref["diagnostics"]
