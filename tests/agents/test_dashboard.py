"""The Rerun recording a run leaves behind, read back with Rerun's own reading API."""

import numpy as np
import pytest

from tests.conftest import SCENARIOS

rr = pytest.importorskip("rerun")
pytest.importorskip("datafusion", reason="reading .rrd files needs rerun-sdk[catalog] (the test extra)")


def read_rrd(path):
    with rr.server.Server(datasets={"run": [str(path)]}) as srv:
        client = srv.client()  # must outlive the query
        df = client.get_dataset("run").reader(index="k").to_pandas()
        del client
        return df


def rows(df, col):
    return df[["k", col]].dropna()


def test_mitra_recording_has_every_series_map_and_graph(run_rse, tmp_path):
    out = tmp_path / "run"
    res = run_rse("simulate", str(SCENARIOS / "mitra_cells.toml"), "--out", str(out), "--no-progress",
                  "--set", "run.rounds=40", "--set", "expect=[]")
    assert res.returncode == 0, res.stderr
    df = read_rrd(out / "recording.rrd")
    for block in ("x", "cell1", "cell2", "cell3", "cell4"):
        s = rows(df, f"/errors/{block}:Scalars:scalars")
        assert sorted(s["k"].astype(int)) == list(range(41))  # one row per logged round
        assert all(len(v) == 16 for v in s.iloc[:, 1])  # one series per agent
        r = rows(df, f"/relative_errors/{block}:Scalars:scalars")  # unstable plant: relative errors too
        assert len(r) == 41
    names = rows(df, "/errors/x:SeriesLines:names").iloc[0, 1]
    assert list(names)[4] == "agent 5 (Byzantine)" and list(names)[0] == "agent 1"
    pos = rows(df, "/map/agents:Points2D:positions")
    assert len(pos) == 41 and all(len(p) == 16 for p in pos.iloc[:, 1])
    # mobile agents move along their patrols
    assert not np.allclose(np.stack(pos.iloc[0, 1]), np.stack(pos.iloc[5, 1]))
    assert len(rows(df, "/map/locations:Points2D:positions")) >= 1
    delivered = rows(df, "/map/links/delivered:Arrows2D:origins")
    dropped = rows(df, "/map/links/dropped:Arrows2D:origins")
    assert len(delivered) >= 40 and len(dropped) >= 40
    n_links = 128  # the baseline graph of Fig. 5
    k5 = 5
    d5 = delivered[delivered["k"] == k5].iloc[0, 1]
    x5 = dropped[dropped["k"] == k5].iloc[0, 1]
    assert len(d5) + len(x5) == n_links and len(x5) > 0  # p = 0.32: some links drop
    assert len(rows(df, "/counters/agent1/delivered:Scalars:scalars")) >= 1
    assert len(rows(df, "/state/x1/truth:Scalars:scalars")) == 41
    assert len(rows(df, "/events/attacks:TextLog:text")) >= 1


def test_lee_kim_shim_recording_marks_the_attack_and_plots_the_paper_quantity(run_rse, tmp_path):
    out = tmp_path / "run"
    res = run_rse("simulate", str(SCENARIOS / "lee_kim_shim.toml"), "--out", str(out), "--no-progress",
                  "--set", "run.dt=0.01", "--set", "run.duration=12", "--set", "expect=[]", "--set", "output.window=[10, 12]")
    assert res.returncode == 0, res.stderr
    df = read_rrd(out / "recording.rrd")
    assert len(rows(df, "/errors/x:Scalars:scalars")) == 1201
    text = rows(df, "/events/attacks:TextLog:text")
    assert int(text["k"].iloc[0]) == 1000  # attack starts at t = 10
    assert len(rows(df, "/state/theta_sum/truth:Scalars:scalars")) == 1201
    assert len(rows(df, "/state/theta_sum/agent1:Scalars:scalars")) == 1201


def test_no_rerun_writes_no_recording(run_rse, tmp_path):
    out = tmp_path / "run"
    res = run_rse("simulate", str(SCENARIOS / "mitra_cells.toml"), "--out", str(out), "--no-progress",
                  "--set", "run.rounds=5", "--set", "expect=[]", "--no-rerun")
    assert res.returncode == 0, res.stderr
    assert not (out / "recording.rrd").exists()
