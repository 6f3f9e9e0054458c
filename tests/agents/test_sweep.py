"""``rse sweep``: grid syntax, parallel runs, the table, resuming."""

from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from agents.sweep import parse_grid, points, run_sweep
from estimation.errors import ScenarioError

SC = Path(__file__).resolve().parents[2] / "scenarios" / "mitra_cells.toml"


def test_grid_syntax():
    key, vals = parse_grid("network.channel.drop_p=0:0.9:0.05")
    assert key == "network.channel.drop_p" and len(vals) == 19 and vals[0] == 0 and vals[-1] == pytest.approx(0.9)
    assert parse_grid("estimator.rule=lfre,median")[1] == ["lfre", "median"]
    assert parse_grid("plant.params.K=2:8:2")[1] == [2, 4, 6, 8]
    for bad in ("nokey", "a=1:0:1", "a=x:y:z", "=3"):
        with pytest.raises(ScenarioError):
            parse_grid(bad)
    pts = points([("a", [1, 2]), ("b", ["x", "y", "z"])], [0, 1])
    assert len(pts) == 12 and len({p.id for p in pts}) == 12


def test_sweep_runs_in_parallel_writes_the_table_and_resumes(tmp_path):
    out = tmp_path / "sweep"
    calls = []
    rows = run_sweep(SC, ["network.channel.drop_p=0.0,0.8"], seeds=2, jobs=2, out=out,
                     overrides=["run.rounds=60", "expect=[]"], progress=lambda d, t: calls.append((d, t)))
    assert len(rows) == 4 and all(r["status"] == "ok" for r in rows)
    table = pq.read_table(out / "sweep.parquet").to_pydict()
    assert sorted(table["network.channel.drop_p"]) == [0.0, 0.0, 0.8, 0.8]
    assert sorted(table["seed"]) == [3, 3, 4, 4]
    by_p = {}
    for p, e in zip(table["network.channel.drop_p"], table["worst_final_error_2"]):
        by_p.setdefault(p, []).append(e)
    assert max(by_p[0.0]) < min(by_p[0.8])  # dropping 80% of the messages hurts
    assert calls[0] == (0, 4) and calls[-1] == (4, 4)
    # resume: everything is done already, nothing runs again
    stamps = {p: p.stat().st_mtime_ns for p in out.glob("points/*/point.json")}
    calls.clear()
    rows2 = run_sweep(SC, ["network.channel.drop_p=0.0,0.8"], seeds=2, jobs=2, out=out,
                      overrides=["run.rounds=60", "expect=[]"], progress=lambda d, t: calls.append((d, t)))
    assert calls == [(4, 4)] and len(rows2) == 4
    assert stamps == {p: p.stat().st_mtime_ns for p in out.glob("points/*/point.json")}
    # a different sweep in the same directory is refused
    with pytest.raises(ScenarioError, match="holds a different sweep"):
        run_sweep(SC, ["network.channel.drop_p=0.1"], seeds=2, jobs=1, out=out, overrides=["run.rounds=60", "expect=[]"])


def test_bad_grid_values_fail_before_any_run(tmp_path):
    with pytest.raises(ScenarioError, match="drop_p"):
        run_sweep(SC, ["network.channel.drop_p=0.5,1.5"], seeds=1, jobs=1, out=tmp_path / "s", overrides=["expect=[]"])
    assert not (tmp_path / "s").exists()


def test_each_run_is_tagged_in_its_recording_and_rse_report_prints_the_sweep(tmp_path, run_rse):
    rr = pytest.importorskip("rerun")
    pytest.importorskip("datafusion", reason="reading .rrd files needs rerun-sdk[catalog] (the test extra)")
    from tests.agents.test_dashboard import read_rrd

    out = tmp_path / "sweep"
    rows = run_sweep(SC, ["network.channel.drop_p=0.0,0.8"], seeds=1, jobs=2, out=out,
                     overrides=["run.rounds=40", "expect=[]"])
    # every run of the sweep in one dataset (as in one viewer), one segment per run, found by its tags
    files = sorted(str(f) for f in out.glob("points/*/run.rrd"))
    assert len(files) == 2
    with rr.server.Server(datasets={"sweep": files}) as srv:
        client = srv.client()
        seg = client.get_dataset("sweep").segment_table().to_pandas()
        del client
    tags = {str(r["property:sweep:point"][0]): r for _, r in seg.iterrows()}
    for row in rows:
        t = tags[row["point"]]
        assert t["property:sweep:network_channel_drop_p"][0] == pytest.approx(row["network.channel.drop_p"])
        assert t["property:sweep:seed"][0] == row["seed"]
        assert t["property:RecordingInfo:name"][0] == f"drop_p={row['network.channel.drop_p']} seed={row['seed']}"
        df = read_rrd(out / "points" / row["point"] / "run.rrd")
        worst = df[["k", "/worst/relative_error_2/x:Scalars:scalars"]].dropna()
        assert len(worst) == 41
        final = worst["/worst/relative_error_2/x:Scalars:scalars"].iloc[-1]
        assert float(np.ravel(final)[0]) == pytest.approx(np.log10(row["worst_final_relative_error_2"]))
    rep = run_rse("report", str(out), cwd=tmp_path)
    assert rep.returncode == 0, rep.stderr
    assert "2 runs, 2 points" in rep.stdout and "0.8" in rep.stdout
