"""The batched simulator path equals the per-agent one for every batchable algorithm.

``simulate(batched=True)`` steps the agents whose estimators declare
:class:`estimation.batching.Batchable` in one stacked call per round;
``simulate(batched=False)`` calls each agent's own ``step`` (the reference, and what
``rse run`` computes). Each case states the agreement its algorithm documents: bit for bit
(``exact``) or within 1e-12 relative to the largest estimate (``rel``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from agents.api import load_experiment
from agents.simulate import batch_groups, closed_team, make_channel, make_nodes, simulate
from estimation.base import Received

SCEN = Path(__file__).resolve().parents[2] / "scenarios"
REL = 1e-12
BYZ_LKS = 'attacks=[{target="agent", agents=[2], kind="constant", value=5.0}]'
BYZ_MAO = ('attacks=[{target="sensor", sensors=[3, 6], kind="trajectory", x0_attack=[-2.0, 1.5, -1.0, 2.5]}, '
           '{target="agent", agents=[2], kind="constant", value=5.0}]')
BYZ_UGR = 'attacks=[{target="agent", agents=[4], kind="constant", value=3.0}]'
BYZ_INV = 'attacks=[{target="agent", agents=[3], kind="constant", value=50.0}]'
CHANNEL = ("network.channel.drop_p=0.3", "network.channel.delay_max=2")

CASES = [
    # Lee-Kim-Shim: the median (6), Lyapunov (11) and linear variants, the held sgn;
    # a closed team (perfect channel, honest agents) and drops + delays + a Byzantine agent
    ("lee_kim_shim.toml", ("run.duration=8",), "rel", True),
    ("lee_kim_shim.toml", ("run.duration=8", 'estimator.variant="lyapunov"'), "rel", True),
    ("lee_kim_shim.toml", ("run.duration=8", 'estimator.variant="linear"'), "rel", True),
    ("lee_kim_shim.toml", ("run.duration=8", 'estimator.sign="held"'), "rel", True),
    ("lee_kim_shim.toml", ("run.duration=8", *CHANNEL, BYZ_LKS), "rel", False),
    ("lee_kim_shim_nonresilient.toml", ("run.duration=8", *CHANNEL), "rel", False),
    # Mao-Tabuada: windows, consensus (6)-(10) and the secure decoder; the least-squares baseline
    ("mao_tabuada.toml", ("run.rounds=200",), "exact", True),
    ("mao_tabuada.toml", ("run.rounds=200", *CHANNEL, BYZ_MAO), "exact", False),
    ("mao_tabuada.toml", ("run.rounds=120", 'estimator.decoder="least_squares"'), "exact", True),
    # Ugrinovskii: controlled observers with detectors under the biasing attack, the baseline
    ("ugrinovskii_biasing.toml", ("run.duration=5", "output.window=[4.0, 5.0]"), "rel", True),
    ("ugrinovskii_baseline.toml", ("run.duration=5", "output.window=[4.0, 5.0]"), "rel", True),
    ("ugrinovskii_biasing.toml", ("run.duration=5", "output.window=[4.0, 5.0]", *CHANNEL, BYZ_UGR), "rel", False),
    # the inverter line: the substation's bank of observers (9) and the median (5); the
    # distributed median over a perfect channel, and with drops, delays and a Byzantine agent
    ("inverters_median.toml", ("run.duration=4",), "rel", True),
    ("inverters_distributed.toml", ("run.duration=4",), "rel", True),
    ("inverters_distributed.toml", ("run.duration=4", *CHANNEL, BYZ_INV), "rel", False),
]


def _ids(c) -> str:
    return f"{c[0]}:{'/'.join(c[1])}"


@pytest.mark.parametrize("name,overrides,agree,closed", CASES, ids=[_ids(c) for c in CASES])
def test_batched_equals_per_agent(name: str, overrides: tuple[str, ...], agree: str, closed: bool) -> None:
    exp, _ = load_experiment(SCEN / name, (*overrides, "expect=[]"), None)
    nodes = make_nodes(exp, make_channel(exp))
    groups = batch_groups(exp, nodes)
    assert sum(len(g.agents) for g in groups) == exp.N - len(exp.byzantine), "every regular agent is batched"
    assert (closed_team(exp, nodes, groups, make_channel(exp)) is not None) == closed
    a = simulate(exp, keep_trajectories=True, batched=True)
    b = simulate(exp, keep_trajectories=True, batched=False)
    regular = a.regular
    ea, eb = a.estimates[:, regular], b.estimates[:, regular]
    if agree == "exact":
        assert np.array_equal(ea, eb)
    else:
        scale = np.max(np.abs(eb))
        assert np.max(np.abs(ea - eb)) <= REL * scale
    assert a.links == b.links
    # the diagnostics and attack flags the monitor read from the members
    ma, mb = a.monitor, b.monitor
    assert sorted(ma.diagnostics) == sorted(mb.diagnostics)
    for name in mb.diagnostics:
        ref = mb.diagnostics[name]
        tol = REL * max(1.0, float(np.nanmax(np.abs(ref))) if np.isfinite(ref).any() else 1.0)
        np.testing.assert_allclose(ma.diagnostics[name], ref, rtol=0, atol=tol, equal_nan=True)
    assert (ma.flags is None) == (mb.flags is None)
    if mb.flags is not None:
        np.testing.assert_array_equal(ma.flags, mb.flags)
    # the runs are not trivial: estimates move, and agents differ
    assert np.ptp(eb, axis=0).max() > 0
    assert eb.shape[1] == 1 or np.ptp(eb, axis=1).max() > 0


def _lks_team() -> tuple:
    """``lee_kim_shim.toml``'s five estimators twice (``per``, stepped one by one, and
    ``ests``, the members of the batch ``g``), their in-neighbours and the plant."""
    from agents.plant import PlantRole

    exp, _ = load_experiment(SCEN / "lee_kim_shim.toml", ("run.duration=1", "expect=[]"), None)
    per = [exp.make_estimator(i) for i in range(exp.N)]
    ests = [exp.make_estimator(i) for i in range(exp.N)]
    nbrs = [list(exp.in_neighbours(i)) for i in range(exp.N)]
    g = type(ests[0]).batch(ests, in_neighbours=nbrs, agents=list(range(exp.N)), rows=exp.agent_rows)
    return exp, per, ests, nbrs, g, PlantRole(exp)


def test_closed_step_and_sync_match_the_per_agent_steps() -> None:
    # step_closed is the per-agent round with every in-neighbour's previous payload in the
    # inbox; sync writes the stacked state back (estimate and partial estimate)
    exp, per, ests, nbrs, g, plant = _lks_team()
    last = None
    for k in range(60):
        y = plant.measure(k)
        inbox = [{} if last is None else {j: Received(j, k - 1, last[j]) for j in nb} for nb in nbrs]
        last = [e.step(k, y[exp.agent_rows[i]], inbox[i]) for i, e in enumerate(per)]
        X = g.step_closed(k, y)
        np.testing.assert_allclose(X, np.array(last), rtol=0, atol=REL * np.max(np.abs(last)))
        plant.advance(k)
    g.sync()
    for a, b in zip(ests, per):
        np.testing.assert_allclose(a.estimate, b.estimate, rtol=0, atol=1e-12)
        np.testing.assert_allclose(a.partial_estimate, b.partial_estimate, rtol=0, atol=1e-12)
    assert np.ptp(np.array(last), axis=0).max() > 0
    # the synced estimators carry on per agent from where the batch stopped
    y = plant.measure(60)
    for i, (a, b) in enumerate(zip(ests, per)):
        inbox = {j: Received(j, 59, last[j]) for j in nbrs[i]}
        np.testing.assert_allclose(a.step(60, y[exp.agent_rows[i]], inbox), b.step(60, y[exp.agent_rows[i]], inbox),
                                   rtol=0, atol=1e-12)


def test_a_batch_over_skipped_rounds_equals_the_per_agent_steps() -> None:
    # a packed realtime process that fell behind steps its batch from round 40 to 75 in one
    # call: as each member's own step, the measurement of round 40 over the first step only
    # and each in-neighbour's estimate over the steps from its stamp on (70: the last five
    # steps; 38: the first two, max_age 3)
    exp, per, _, nbrs, g, plant = _lks_team()
    last: list = []
    for k in range(41):
        y = plant.measure(k)
        inbox = [{j: Received(j, k - 1, last[j]) for j in nb} if last else {} for nb in nbrs]
        last = [e.step(k, y[exp.agent_rows[i]], inbox[i]) for i, e in enumerate(per)]
        got = g.step(k, [y[r] for r in exp.agent_rows], inbox)
        np.testing.assert_allclose(np.array(got), np.array(last), rtol=0, atol=REL * np.max(np.abs(last)))
        plant.advance(k)
    for k in range(41, 75):
        plant.advance(k)
    y = plant.measure(75)
    inbox = [{j: Received(j, 70 if j % 2 else 38, last[j] + 0.1 * (j + 1)) for j in nb} for nb in nbrs]
    want = np.array([e.step(75, y[exp.agent_rows[i]], inbox[i]) for i, e in enumerate(per)])
    got = np.array(g.step(75, [y[r] for r in exp.agent_rows], inbox))
    np.testing.assert_allclose(got, want, rtol=0, atol=REL * np.max(np.abs(want)))
    assert np.abs(want - np.array(last)).max() > 1e-3  # the gap moved them
