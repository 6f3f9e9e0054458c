"""``rse report``: the table, the figures and the comparison of two runs."""

import pytest

from tests.conftest import SCENARIOS


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory):
    from tests.conftest import rse

    root = tmp_path_factory.mktemp("runs")
    for name in ("lee_kim_shim", "lee_kim_shim_nonresilient"):
        res = rse("simulate", str(SCENARIOS / f"{name}.toml"), "--out", str(root / name), "--no-progress",
                  "--no-rerun", "--set", "run.dt=0.01")
        assert res.returncode == 0, res.stderr
    return root / "lee_kim_shim", root / "lee_kim_shim_nonresilient"


def test_report_table_lists_every_agent_and_block(run_rse, two_runs):
    res = run_rse("report", str(two_runs[0]))
    assert res.returncode == 0, res.stderr
    out = res.stdout
    assert "lee_kim_shim (simulate): 4000 rounds, window [30, 40]" in out
    for col in ("final |e|_inf", "window max |e|_inf", "converged at round", "in-links delivered/dropped/late/rejected"):
        assert col in out
    table, expectations = out.split("\nexpectations", 1)
    lines = [l for l in table.splitlines() if l.strip().startswith("│")]
    assert len(lines) == 10  # 5 agents x blocks (x, angles)
    assert [l.split("│")[1].strip() for l in expectations.splitlines() if l.strip().startswith("│ ok")] == ["ok", "ok"]
    assert "0.2165" in out  # agent 1's window maximum
    assert "8002/0/0/0" in out  # two in-links x 4001 rounds, no drops


def test_report_compares_two_runs_and_writes_figures(run_rse, two_runs, tmp_path):
    png = tmp_path / "png"
    res = run_rse("report", str(two_runs[0]), str(two_runs[1]), "--png", str(png))
    assert res.returncode == 0, res.stderr
    assert "worst regular agent: lee_kim_shim vs lee_kim_shim_nonresilient" in res.stdout
    assert "0.4947" in res.stdout  # the biased baseline
    for f in ("errors.png", "state_theta_sum.png", "compare.png"):
        p = png / f
        assert p.exists() and p.stat().st_size > 10_000
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_report_on_a_missing_directory_is_a_clear_error(run_rse, tmp_path):
    res = run_rse("report", str(tmp_path / "nope"))
    assert res.returncode == 2
    assert "not a run directory" in res.stderr and "Traceback" not in res.stderr
    (tmp_path / "half").mkdir()
    (tmp_path / "half" / "manifest.json").write_text("{}")
    res = run_rse("report", str(tmp_path / "half"))
    assert res.returncode == 2 and "missing summary.json, metrics.parquet" in res.stderr


def test_report_table_is_the_same_for_both_drivers(tmp_path):
    """A run directory written by the networked roles (over the in-memory bus, the same
    protocol as `rse run`) reports the same table as one written by `rse simulate`."""
    import asyncio

    from agents.api import load_experiment
    from agents.net.roles import RunConfig, run_team_in_memory
    from agents.report import load_run, table_rows
    from agents.rundir import write_json, write_metrics
    from agents.simulate import simulate
    from agents.summary import evaluate, summarise

    ov = ("run.dt=0.01", "run.duration=12", "output.window=[8.0, 12.0]", "expect=[]")
    exp, _ = load_experiment(SCENARIOS / "lee_kim_shim.toml", ov, None)
    sim_dir = tmp_path / "sim"
    sim_dir.mkdir()
    res = simulate(exp)
    write_metrics(sim_dir, exp, res.monitor, res.regular)
    summ = summarise(exp, res.monitor, res.regular, res.links)
    summ["expectations"] = [r.as_dict() for r in evaluate(exp, res.monitor, res.regular)]
    write_json(sim_dir / "summary.json", summ)
    write_json(sim_dir / "manifest.json", {"driver": "simulate", "scenario": {"run": {"name": "lee_kim_shim"}}})
    exp, _ = load_experiment(SCENARIOS / "lee_kim_shim.toml", ov, None)
    net_dir = tmp_path / "net"
    asyncio.run(asyncio.wait_for(run_team_in_memory(exp, RunConfig(deadline=30.0), out_dir=net_dir), 600))
    write_json(net_dir / "manifest.json", {"driver": "run", "scenario": {"run": {"name": "lee_kim_shim"}}})  # the launcher's part
    a, b = load_run(sim_dir), load_run(net_dir)
    rows = table_rows(a)
    assert len(rows) == 10 and rows == table_rows(b)
