"""The optional estimator capabilities :class:`~estimation.base.Diagnostics`
(``diagnostics() -> dict[str, float]``) and :class:`~estimation.base.Flags` (a ``flagged``
property), declared by inheriting them, recorded per round by the monitor, written to ``diagnostics.parquet`` and
summarised in ``summary.json`` (``diagnostics``, ``detected_attacks``)."""

from __future__ import annotations

import json

import numpy as np
import pyarrow.parquet as pq

from agents.console import summary_table
from agents.monitor import has_diagnostics, read_diagnostics
from agents.rundir import write_json, write_metrics
from agents.simulate import simulate
from agents.summary import summarise
from estimation.base import Diagnostics, Flags
from scenarios.build import build
from scenarios.loader import load
from tests.conftest import SCENARIOS

LKS = SCENARIOS / "lee_kim_shim.toml"


class Flagging(Diagnostics, Flags):
    """Wraps an estimator: reports its round and raises a flag on agent 2 from round 3."""

    def __init__(self, inner, agent: int) -> None:
        self.inner, self.agent, self.k = inner, agent, -1

    @property
    def estimate(self):
        return self.inner.estimate

    def step(self, k, measurement, inbox):
        self.k = k
        return self.inner.step(k, measurement, inbox)

    def diagnostics(self):
        return {"round": float(self.k), "indicator": 0.5 * self.agent}

    @property
    def flagged(self) -> bool:
        return self.agent == 2 and self.k >= 3


class OnlyFlag(Flags):
    def __init__(self, inner) -> None:
        self.inner = inner

    @property
    def estimate(self):
        return self.inner.estimate

    def step(self, k, measurement, inbox):
        return self.inner.step(k, measurement, inbox)

    @property
    def flagged(self) -> bool:
        return False


def short_lks():
    sc, _ = load(LKS, ["run.duration=0.01", "expect=[]", "output.window=[0, 0.01]", "run.dt=0.001"])
    return build(sc, source="lks")


def test_has_and_read_diagnostics():
    exp = short_lks()
    est = exp.make_estimator(0)
    assert not has_diagnostics(est) and read_diagnostics(est) == (None, None)
    w = Flagging(est, 2)
    w.k = 5
    assert has_diagnostics(w) and read_diagnostics(w) == ({"round": 5.0, "indicator": 1.0}, True)
    assert has_diagnostics(OnlyFlag(est)) and read_diagnostics(OnlyFlag(est)) == (None, False)


def test_an_undeclared_method_is_not_a_capability():
    """A ``diagnostics`` method on a class that does not declare the capability is not read."""

    class Undeclared:
        def diagnostics(self):
            return {"x": 1.0}

        flagged = True

    assert not has_diagnostics(Undeclared()) and read_diagnostics(Undeclared()) == (None, None)


def test_monitor_records_and_the_run_directory_reports(tmp_path, monkeypatch):
    exp = short_lks()
    plain = simulate(exp)
    assert plain.monitor.diagnostics == {} and plain.monitor.flags is None
    s = summarise(exp, plain.monitor, plain.regular, plain.links)
    assert "diagnostics" not in s and "detected_attacks" not in s  # nothing new without the hook
    write_metrics(tmp_path, exp, plain.monitor, plain.regular)
    assert not (tmp_path / "diagnostics.parquet").exists()

    make = type(exp).make_estimator

    def wrapped(self, i):
        inner = make(self, i)
        return Flagging(inner, self.agent_ids[i]) if i < 3 else (OnlyFlag(inner) if i == 3 else inner)

    monkeypatch.setattr(type(exp), "make_estimator", wrapped)
    res = simulate(exp)
    mon = res.monitor
    assert set(mon.diagnostics) == {"round", "indicator"}
    assert mon.diagnostics["round"][:, 0].tolist() == list(range(11))
    assert np.all(np.isnan(mon.diagnostics["round"][:, 3:]))  # agents 4, 5 report no diagnostics
    assert np.all(np.isnan(mon.flags[:, 4])) and np.all(mon.flags[:, 3] == 0.0)
    assert mon.flags[:, 1].tolist() == [0.0] * 3 + [1.0] * 8
    s = summarise(exp, mon, res.regular, res.links)
    assert s["detected_attacks"]["agents"] == [2]
    rec = s["detected_attacks"]["by_agent"]["2"]
    assert rec == {"flagged_rounds": 8, "first_t": 3 * exp.dt, "last_t": 10 * exp.dt, "flagged_at_end": True}
    assert set(s["detected_attacks"]["by_agent"]) == {"1", "2", "3", "4"}
    assert s["diagnostics"]["3"]["indicator"] == {"final": 1.5, "max_abs": 1.5, "window_max_abs": 1.5}
    assert "5" not in s["diagnostics"]
    write_json(tmp_path / "summary.json", s)
    assert json.loads((tmp_path / "summary.json").read_text())["detected_attacks"]["agents"] == [2]
    write_metrics(tmp_path, exp, mon, res.regular)
    table = pq.read_table(tmp_path / "diagnostics.parquet").to_pydict()
    assert len(table["k"]) == 11 * exp.N
    assert set(table) == {"k", "t", "agent", "flagged", "round", "indicator"}
    flagged = {(k, a): f for k, a, f in zip(table["k"], table["agent"], table["flagged"])}
    assert flagged[(5, 2)] is True and flagged[(2, 2)] is False and flagged[(5, 5)] is None
    caption = summary_table(s).caption
    assert caption.startswith("attack flags: agent 2 (t = 0.003 .. 0.01)")
