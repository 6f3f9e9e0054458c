"""``rse chaos``'s schedule and measurements, without processes: the schedule is a function
of the seed and covers every kind, and the measurement of a fault reads what the record
says (docs/chaos.md)."""

from __future__ import annotations

import collections

import numpy as np
import pytest

from agents.chaos import BUDGETS, KINDS, Fault, parse_budgets, parse_kinds, plan_faults
from agents.chaos.measure import recovered_round, undeclared_rounds
from estimation.errors import ScenarioError
from tests.conftest import SCENARIOS

RING = dict(agents=[1, 2, 3, 4, 5], links=[(1, 2), (2, 3), (3, 4), (4, 5), (1, 5)])


def soak(seed: int = 1, episodes=(300.0,), **kw):
    args = dict(kinds=KINDS, spacing=10.0, settle=20.0, tail=5.0) | kw
    return plan_faults(episodes=list(episodes), seed=seed, **RING, **args)


def test_the_schedule_is_a_function_of_the_seed():
    assert soak(1) == soak(1)
    assert soak(1) != soak(2)
    assert [f.as_dict() for f in soak(7)] == [f.as_dict() for f in soak(7)]


def test_a_300_s_soak_holds_every_kind_at_least_five_times_one_per_slot():
    faults = soak(1)
    counts = collections.Counter(f.kind for f in faults)
    assert set(counts) == set(KINDS) and min(counts.values()) >= 5
    assert len(faults) == 27  # (300 - 20 - 5) / 10 slots
    ats = [f.at for f in faults]
    assert ats == [20.0 + 10.0 * i for i in range(27)]
    for f, nxt in zip(faults, faults[1:]):
        assert f.until == nxt.at and f.at + f.lasts <= f.until - 6.0  # its recovery is looked for before the next
    assert faults[-1].until == 300.0


def test_each_fault_names_a_target_of_its_kind():
    for f in soak(3):
        if f.kind in ("kill-agent", "freeze-agent"):
            assert len(f.agents) == 1 and f.agents[0] in RING["agents"]
        elif f.kind == "cut-link":
            assert tuple(f.agents) in RING["links"]
        else:
            assert f.agents == ()
        assert f.hogs == (2 if f.kind == "cpu-hog" else 0)
        assert f.budget == BUDGETS[f.kind]


def test_episodes_each_get_their_own_slots_and_the_kinds_keep_cycling():
    faults = soak(1, episodes=(95.0, 95.0, 95.0, 95.0))
    per = collections.Counter(f.episode for f in faults)
    assert per == {0: 7, 1: 7, 2: 7, 3: 7}
    assert min(collections.Counter(f.kind for f in faults).values()) >= 5
    assert all(f.until <= 95.0 for f in faults)


def test_kinds_and_budgets_are_parsed_with_clear_errors():
    assert parse_kinds("kill-agent, cut-link") == ("kill-agent", "cut-link")
    assert parse_kinds(None) == KINDS
    with pytest.raises(ScenarioError, match="unknown fault kind.*explode.*valid: kill-agent"):
        parse_kinds("kill-agent,explode")
    assert parse_budgets(["kill-agent=12"])["kill-agent"] == 12.0
    with pytest.raises(ScenarioError, match="--budget kill=3: unknown fault kind"):
        parse_budgets(["kill=3"])
    with pytest.raises(ScenarioError, match="expected KIND=SECONDS"):
        parse_budgets(["cut-link=soon"])


def test_a_cut_needs_a_link():
    with pytest.raises(ScenarioError, match="no link between two regular agents"):
        plan_faults(episodes=[60.0], kinds=("cut-link",), seed=1, agents=[1], links=[], spacing=10, settle=5, tail=5)


def test_recovery_is_the_first_round_after_the_last_excursion():
    err = np.full((100, 2), 0.1)
    err[40:45, 0] = np.nan  # the fault: no report
    err[45:52, 0] = 2.0  # back, out of bound
    err[30:60:7, 1] = np.nan  # a realtime agent skipping rounds now and then: not out of bound
    assert recovered_round(err, 0.25, 40, 45, 90, hold=10) == 52
    err[78:, 0] = np.nan  # stopped reporting over the last hold rounds before the next fault: not recovered
    assert recovered_round(err, 0.25, 40, 45, 90, hold=10) is None
    err[78:, 0] = 0.1
    err[70, 1] = 0.3  # a later excursion counts too
    assert recovered_round(err, 0.25, 40, 45, 90, hold=10) == 71


def test_missing_reports_outside_the_declared_gaps_are_counted():
    class Rec:
        agent_ids = [1, 2]
        err = np.full((50, 2), 0.1)

        def cols(self, agents):
            return [self.agent_ids.index(a) for a in agents]

    rec = Rec()
    rec.err[10:20, 0] = np.nan
    rec.err[30, 1] = np.nan
    assert undeclared_rounds(rec, [1, 2], [(8, 21)]) == 1
    assert undeclared_rounds(rec, [1, 2], []) == 11


def test_fault_targets_read_well():
    f = Fault(0, "cut-link", 0, 10.0, 2.0, (1, 5), 6.0, 20.0)
    assert f.target == "link 1<->5" and f.as_dict()["agents"] == [1, 5]


@pytest.mark.parametrize("args, message", [
    (["--faults", "kill-agent,explode"], "--faults: unknown fault kind(s) explode; valid: kill-agent"),
])
def test_bad_input_exits_2_with_one_line(run_rse, tmp_path, args, message):
    res = run_rse("chaos", str(SCENARIOS / "lee_kim_shim.toml"), "--duration", "30", *args, "--out", str(tmp_path / "c"))
    assert res.returncode == 2, res.stderr
    assert message in res.stderr and "Traceback" not in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1


def test_the_faults_are_marked_on_the_runs_timeline(tmp_path):
    rr = pytest.importorskip("rerun")
    pytest.importorskip("datafusion", reason="reading .rrd files needs rerun-sdk[catalog] (the test extra)")
    from agents.dashboard import log_fault_marks

    path = tmp_path / "chaos.rrd"
    log_fault_marks(path, run_id="team-1", dt=0.01, marks=[(250, "fault 0: kill-agent agent 3 begins"),
                                                          (120, "fault 1: cut-link link 1<->2 ends")])
    with rr.server.Server(datasets={"run": [str(path)]}) as srv:
        client = srv.client()
        df = client.get_dataset("run").reader(index="k").to_pandas()
        del client
    marks = df[["k", "/events/faults:TextLog:text"]].dropna()
    assert [(int(k), list(t)[0]) for k, t in marks.itertuples(index=False)] == [
        (120, "fault 1: cut-link link 1<->2 ends"), (250, "fault 0: kill-agent agent 3 begins")]


def test_a_fault_not_recovered_says_what_the_record_shows():
    from agents.chaos.measure import _why

    err = np.full((100, 2), 0.1)
    err[80:, :] = np.nan  # a monitor not back yet
    assert _why(err, 0.25, 40, 90, 10) == "no report recorded in the last second before the next fault"
    err[80:, :] = 0.1
    err[60:, 1] = 0.4
    assert _why(err, 0.25, 40, 90, 10) == "an affected agent still out of bound (0.4) at the next fault"
