"""Realtime health: message ages and lateness per link (agents.net.health), the summary's
``health`` and the line that says a run did not keep its rate (agents.health), and a real
realtime team that cannot keep its rate saying so."""

import json
import re
from types import SimpleNamespace

import numpy as np
import pytest

from agents.health import health_rows, health_section, rate_line
from agents.net.health import EDGES, LinkHealth, percentile_ms
from tests.conftest import SCENARIOS


def test_ages_are_measured_from_the_start_of_the_round_a_message_carries_to_its_use():
    h = LinkHealth([2, 3], period=0.01)
    h.measured(10, 100.000)
    h.measured(11, 100.010)
    h.arrived(2, 10, last=10)  # before round 11 ran: on time
    h.arrived(3, 10, last=11)  # after round 11 ran: late
    h.used(100.025)  # the round that takes both in starts 25 ms after round 10 did
    rows = {int(r[0]): r for r in h.ages_rows()}
    for j in (2, 3):
        assert rows[j][1] == pytest.approx(25.0, rel=0.05) and rows[j][2] == pytest.approx(25.0, rel=0.05)
        assert rows[j][3] == 1
    assert rows[2][4] == 0 and rows[3][4] == 1


def test_a_round_not_measured_here_is_dated_from_the_plants_period():
    h = LinkHealth([2], period=0.01)
    h.measured(20, 50.0)
    h.arrived(2, 15, last=20)  # round 15's start is not known: 5 periods before round 20's
    h.used(50.0)
    assert h.ages_rows()[0, 1] == pytest.approx(50.0, rel=0.05)


def test_percentiles_read_the_histogram_and_an_unused_link_has_none():
    hist = np.zeros(len(EDGES) + 1, dtype=np.int64)
    assert percentile_ms(hist, 50) is None
    for age in [0.001] * 98 + [0.5, 0.5]:
        hist[int(np.searchsorted(EDGES, age, side="right"))] += 1
    assert percentile_ms(hist, 50) == pytest.approx(1.0, rel=0.05)
    assert percentile_ms(hist, 99) == pytest.approx(500.0, rel=0.05)
    h = LinkHealth([4], period=0.01)
    assert h.ages_rows().tolist() == [[4.0, -1.0, -1.0, 0.0, 0.0, 0.0]]  # the wire carries no NaN


def test_a_live_neighbour_silent_for_a_second_and_10_rounds_is_a_stall_counted_once():
    h = LinkHealth([2, 3], period=0.01)
    live = {2, 3}.__contains__
    assert h.stalled(0, 0.0, live) == []
    assert h.stalled(9, 5.0, live) == []  # 5 s but 9 rounds
    assert h.stalled(10, 0.5, live) == []  # 10 rounds but half a second
    assert h.stalled(10, 1.0, live) == [2, 3]
    assert h.stalled(50, 9.0, live) == []  # the same silence
    h.arrived(2, 50, last=50)  # agent 2 speaks again: its silence ended
    assert h.stalled(60, 10.0, live) == [] and h.stalled(70, 11.0, live) == [2]
    h.arrived(3, 70, last=70)
    assert h.stalled(100, 20.0, lambda j: j != 3) == []  # agent 3 left: its token is gone
    assert {int(r[0]): int(r[5]) for r in h.ages_rows()} == {2: 2, 3: 1}


def _stats(meta, ages=None, out=None):
    arrays = {"ages": np.array(ages or [], dtype=float).reshape(-1, 6), "out": np.array(out or [], dtype=float).reshape(-1, 2)}
    return SimpleNamespace(meta=meta, arrays=arrays)


def test_the_summary_joins_senders_and_receivers_and_says_the_rate_was_not_kept():
    stats = {"plant": _stats({"rounds": 100}),
             "1": _stats({"rounds": 60, "skipped": 40}, ages=[[2, 12.0, 40.0, 50, 3, 1]], out=[[2, 60]]),
             "2": _stats({"rounds": 100, "skipped": 0}, ages=[[1, 10.0, 20.0, 55, 0, 0]], out=[[1, 100]])}
    links = {"2->1": {"sent": 97, "delivered": 60, "dropped": 37, "late": 1, "rejected": 0},
             "1->2": {"sent": 60, "delivered": 40, "dropped": 20, "late": 0, "rejected": 0}}
    h = health_section(stats, [1, 2], links, mode="realtime", rate=100.0, deadline_misses=0)
    assert h["agents"] == {"1": {"rounds": 60, "skipped": 40, "skip_fraction": 0.4},
                           "2": {"rounds": 100, "skipped": 0, "skip_fraction": 0.0}}
    assert h["skip_fraction"] == 0.2 and h["kept_rate_hz"] == 80.0 and h["kept"] is False
    assert h["links"]["2->1"] == {"sent": 100, "arrived": 97, "lost_model": 37, "lost_transport": 3, "late": 4,
                                  "stalls": 1, "age_p50_ms": 12.0, "age_p99_ms": 40.0}
    assert h["links"]["1->2"]["lost_transport"] == 0
    line = rate_line({"health": h})
    assert line == ("the machine did not keep 100 Hz: the agents skipped 20.0% of their rounds "
                    "(most: agent 1, 40%); they kept about 80 Hz")
    assert health_rows({"health": h})[0] == ["1", "60", "40", "4", "1", "37", "3", "12.0", "40.0"]
    kept = health_section({k: v for k, v in stats.items() if k != "1"}, [2], links, mode="realtime", rate=100.0,
                          deadline_misses=0)
    assert kept["kept"] is True and rate_line({"health": kept}) is None
    # a restarted receiver counts from its rejoin, its sender from round 0: no transport loss is inferred
    stats["1"].meta["rejoined"] = True
    again = health_section(stats, [1, 2], links, mode="realtime", rate=100.0, deadline_misses=0)["links"]
    assert again["2->1"]["sent"] == 100 and again["2->1"]["lost_transport"] is None
    assert again["1->2"]["lost_transport"] is None
    lockstep = health_section(stats, [1, 2], links, mode="lockstep", rate=None, deadline_misses=0)
    assert rate_line({"health": lockstep}) is None
    fast = health_section(stats, [1, 2], links, mode="realtime", rate=2000.0, deadline_misses=0)
    assert rate_line({"health": fast}).endswith("they kept about 1600 Hz")  # no exponent


@pytest.mark.slow
def test_a_realtime_team_that_cannot_keep_its_rate_says_so_in_one_line(run_rse, tmp_path):
    """mitra_cells.toml's 16 agents at 2,000 Hz: no 2-core machine keeps that; the run says
    so with the skip fraction and the rate kept, and the summary has every figure per agent
    and per link."""
    out = tmp_path / "run"
    res = run_rse("run", str(SCENARIOS / "mitra_cells.toml"), "--mode", "realtime", "--rate", "2000",
                  "--out", str(out), "--set", "expect=[]", timeout=240)
    assert res.returncode == 0, res.stderr
    m = re.search(r"the machine did not keep 2000 Hz: the agents skipped (\d+\.\d)% of their rounds "
                  r"\(most: agent \d+, \d+%\)(?:; the plant missed \d+ round deadline\(s\))?; they kept about ([\d.]+) Hz", " ".join(res.stdout.split()))
    assert m, res.stdout
    h = json.loads((out / "summary.json").read_text())["health"]
    assert h["mode"] == "realtime" and h["kept"] is False and h["skip_fraction"] > 0
    assert float(m.group(1)) == pytest.approx(100 * h["skip_fraction"], abs=0.06)
    assert float(m.group(2)) == pytest.approx(h["kept_rate_hz"], rel=0.01)
    assert sorted(h["agents"], key=int) == [str(a) for a in range(1, 17)]
    assert all(a["rounds"] + a["skipped"] <= 301 and a["rounds"] > 0 for a in h["agents"].values())
    assert len(h["links"]) == 128  # the baseline graph of Fig. 5
    for c in h["links"].values():
        assert c["sent"] >= c["arrived"] and c["lost_transport"] == c["sent"] - c["arrived"]
        assert c["lost_model"] <= c["arrived"]
    aged = [c for c in h["links"].values() if c["age_p50_ms"] is not None]
    assert len(aged) >= 100 and all(0 < c["age_p50_ms"] <= c["age_p99_ms"] for c in aged)
    assert "age p99 ms" in res.stdout
    # the dashboard: the rounds without a report per agent as they happen, the table at the end
    from tests.agents.test_dashboard import read_rrd

    df = read_rrd(out / "recording.rrd")
    unreported = df[["k", "/health/agent1:Scalars:scalars"]].dropna()
    assert len(unreported) >= 1
    doc = df["/health/summary:TextDocument:text"].dropna()
    assert len(doc) == 1 and "did not keep 2000 Hz" in str(doc.iloc[0])
