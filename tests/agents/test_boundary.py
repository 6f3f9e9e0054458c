"""``rse boundary``: probabilistic bisection over a parameter, its intervals, its files, bad input."""

from __future__ import annotations

import json
import math

import numpy as np
import pyarrow.parquet as pq
import pytest

from agents.boundary import Search, majority_p_value, median_interval, metric_column, parse_vary
from estimation.errors import ScenarioError
from tests.conftest import SCENARIOS

SC = str(SCENARIOS / "mitra_cells.toml")


def test_majority_p_value_is_the_hypergeometric_tail_of_the_least_favourable_split():
    # 5 of 5 sampled below, 10 of 20 seeds below at worst: C(10,5) / C(20,5)
    assert majority_p_value(5, 5, 20) == pytest.approx(math.comb(10, 5) / math.comb(20, 5))
    assert majority_p_value(5, 5, 20) < 0.05 < majority_p_value(4, 5, 20)
    assert majority_p_value(11, 20, 20) == 0.0  # every seed ran: the majority is known
    assert majority_p_value(10, 20, 20) > 0.5   # a tie decides nothing


def test_median_interval_uses_the_order_statistics_of_the_binomial():
    b = [(float(i), float(i) + 0.5) for i in range(1, 21)]
    # 20 seeds at 95%: ranks 6 and 15 (coverage 1 - 2 P(Bin(20, 1/2) <= 5) = 0.9586)
    assert median_interval(b) == (6.0, 15.5)
    assert median_interval(b[:5]) == (-math.inf, math.inf)  # 5 seeds cannot give 95%
    s = Search("k", 0.0, 1.0, list(range(5)), 1e-6)
    assert s.result()["ci_low"] is None and s.result()["ci_high"] is None


def test_search_finds_the_median_crossing_of_twenty_seeds_in_under_a_quarter_of_the_grid():
    """40 synthetic searches: each seed has its own crossing near 0.85 (spread 0.03); the
    target is where the median over the 20 seeds crosses (np.median of 20 values is the
    mean of the 10th and 11th: above 1e-6 once 10 seeds are at 0.5)."""
    covered, errors = 0, []
    for rng_seed in range(40):
        rng = np.random.default_rng(rng_seed)
        crossing = {s: 0.85 + 0.03 * rng.standard_normal() for s in range(20)}  # each seed's own boundary
        order = sorted(crossing.values())
        target = order[9]
        s = Search("network.channel.drop_p", 0.0, 0.95, list(range(20)), 1e-6)
        while not s.done(90):
            batch = s.next_batch()  # a seed's metric: 1e-15 below its crossing, 0.5 above
            s.observe([0.5 if p.values[-1][1] > crossing[p.seed] else 1e-15 for p in batch])
        r = s.result()
        assert r["runs"] <= 90 and r["inside"]  # a quarter of the 380-run grid is 95
        errors.append(abs(r["estimate"] - target))
        covered += r["search_low"] <= target <= r["search_high"]
        # the interval from the seeds is conservative: it holds the 6th and 15th crossings
        assert r["ci_low"] <= order[5] and r["ci_high"] >= order[14], r
    assert max(errors) < 0.025 and float(np.median(errors)) < 0.005, errors
    assert covered >= 34  # the search's 95% interval holds the target (37 of 40 when written)


def test_a_tie_of_the_seeds_is_decided_by_the_median_of_their_metric():
    # 10 seeds converge (1e-15), 10 reach 0.5: the median (2.5e-1) is above 1e-6, so the
    # boundary lies left of the query; the same seeds at the same point never repeat it
    s = Search("k", 0.0, 1.0, list(range(20)), 1e-6)
    xs = []
    while not s.done(80):
        batch = s.next_batch()
        xs.append(s.x)
        s.observe([0.5 if p.seed % 2 else 1e-15 for p in batch])
    assert len(set(xs)) > 3 and s.result()["estimate"] < 0.05


def test_a_boundary_beyond_the_range_ends_at_its_edge():
    s = Search("k", 0.0, 1.0, list(range(10)), 1e-6)
    while not s.done(60):
        s.observe([1e-15] * len(s.next_batch()))  # never above: the crossing lies past HI
    assert s.result()["estimate"] > 0.97 and not s.result()["inside"]


def test_parse_vary_and_metric_names():
    assert parse_vary("network.channel.drop_p=0:0.95") == ("network.channel.drop_p", 0.0, 0.95)
    for bad in ("k=0.5:0.5", "k=0.9:0.1", "k=a:b", "k", "k=0:1:2"):
        with pytest.raises(ScenarioError):
            parse_vary(bad)
    assert metric_column("relative_error_2") == "worst_final_relative_error_2"
    assert metric_column("window_max_error_2") == "worst_window_max_error_2"
    with pytest.raises(ScenarioError, match="unknown metric"):
        metric_column("nope")


@pytest.mark.parametrize("args, words", [
    (["--vary", "network.channel.drop_p=0.5:0.5"], "empty range"),
    (["--vary", "network.channel.nope=0:0.9"], "nope"),
    (["--vary", "network.channel.drop_p=0:0.9", "--metric", "speed"], "unknown metric"),
])
def test_bad_input_is_a_one_line_error(tmp_path, run_rse, args, words):
    r = run_rse("boundary", SC, *args, "--threshold", "1e-6", "--out", str(tmp_path / "b"), cwd=tmp_path)
    assert r.returncode == 2, r.stdout + r.stderr
    assert words in r.stderr and "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1


@pytest.mark.slow
def test_boundary_writes_every_run_the_summary_and_the_figure(tmp_path, run_rse):
    out = tmp_path / "b"
    r = run_rse("boundary", SC, "--vary", "network.channel.drop_p=0:0.95", "--threshold", "1e-6", "--seeds", "5",
                "--max-runs", "15", "--jobs", "2", "--set", "run.rounds=100", "--set", "expect=[]", "--out", str(out),
                cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    meta = json.loads((out / "boundary.json").read_text())
    res = meta["results"][0]
    rows = pq.read_table(out / "boundary.parquet").to_pylist()
    assert len(rows) == res["runs"] and 15 <= res["runs"] <= 20
    assert {r["seed"] for r in rows} <= {3, 4, 5, 6, 7} and all(r["status"] == "ok" for r in rows)
    assert all(r["above"] == (r["worst_final_relative_error_2"] > 1e-6) for r in rows)
    assert (out / "boundary.png").stat().st_size > 10_000
    assert len(list(out.glob("points/*/run.rrd"))) == len({r["point"] for r in rows})
    assert f"network.channel.drop_p = {res['estimate']:.4f}" in r.stdout and res["at"] == {}
    rep = run_rse("report", str(out), cwd=tmp_path)
    assert rep.returncode == 0 and f"boundary {res['estimate']:.4f}" in rep.stdout


@pytest.mark.slow
def test_two_vary_trace_the_boundary_over_a_second_key_beside_the_theory(tmp_path, run_rse):
    out = tmp_path / "curve"
    r = run_rse("boundary", SC, "--vary", "network.channel.drop_p=0:0.95", "--vary", "plant.params.lam_high=1.1,1.3",
                "--threshold", "1e-6", "--seeds", "5", "--max-runs", "10", "--jobs", "2", "--no-rrd",
                "--set", "run.rounds=60", "--set", "expect=[]", "--out", str(out), cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    res = json.loads((out / "boundary.json").read_text())["results"]
    assert [x["at"] for x in res] == [{"plant.params.lam_high": 1.1}, {"plant.params.lam_high": 1.3}]
    assert all(10 <= x["runs"] <= 15 for x in res)
    rows = pq.read_table(out / "boundary.parquet").to_pylist()
    assert sorted({row["plant.params.lam_high"] for row in rows}) == [1.1, 1.3]
    assert len(rows) == sum(x["runs"] for x in res)
    assert "plant.params.lam_high=1.1: network.channel.drop_p = " in r.stdout
    assert (out / "boundary.png").stat().st_size > 10_000


def test_the_public_api_checks_its_input_before_any_run(tmp_path):
    import rse

    with pytest.raises(ScenarioError, match="empty range"):
        rse.boundary(SC, "network.channel.drop_p", (0.5, 0.5), threshold=1e-6, out=tmp_path / "b")
    with pytest.raises(ScenarioError, match="nope"):
        rse.boundary(SC, "network.channel.drop_p", (0.0, 0.9), threshold=1e-6, curve=("estimator.nope", [1, 2]),
                     out=tmp_path / "b")
    assert not (tmp_path / "b").exists()
