"""The command line as a user meets it: exit statuses, messages, no tracebacks."""

import json

import pyarrow.parquet as pq
import pytest

from tests.conftest import SCENARIOS


def no_traceback(res):
    assert "Traceback" not in res.stderr and "Traceback" not in res.stdout


def test_simulate_writes_the_run_directory(run_rse, tmp_path):
    out = tmp_path / "run"
    res = run_rse("simulate", str(SCENARIOS / "lee_kim_shim.toml"), "--out", str(out), "--no-progress",
                  "--set", "run.dt=0.01")
    assert res.returncode == 0, res.stderr
    no_traceback(res)
    assert {p.name for p in out.iterdir()} >= {"manifest.json", "metrics.parquet", "summary.json", "design.json"}
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["seed"] == 1 and manifest["scenario"]["run"]["dt"] == 0.01
    assert "numpy" in manifest["versions"]
    table = pq.read_table(out / "metrics.parquet")
    cols = set(table.column_names)
    assert {"k", "t", "agent", "regular", "block", "error_2", "error_inf", "relative_error_2"} <= cols
    assert table.num_rows == 4001 * 5 * 2  # rounds x agents x blocks (x and angles)
    summary = json.loads((out / "summary.json").read_text())
    w = summary["worst_regular"]["x"]
    assert w["window_max_error_inf"] <= 0.25
    assert set(summary["agents"]) == {"1", "2", "3", "4", "5"}
    assert all(e["ok"] for e in summary["expectations"])
    assert "ok" in res.stdout and "worst agent, max infinity-norm error over [30, 40]" in res.stdout


def test_failed_expectation_has_its_own_exit_status(run_rse, tmp_path):
    res = run_rse("simulate", str(SCENARIOS / "lee_kim_shim.toml"), "--out", str(tmp_path / "r"), "--no-progress",
                  "--set", "run.dt=0.01", "--set", "expect.1.max=0.1")
    assert res.returncode == 3
    no_traceback(res)
    assert "1 of 2 expectation(s) failed" in res.stderr
    assert "FAIL" in res.stdout


@pytest.mark.parametrize(
    "args, message",
    [
        (["does/not/exist.toml"], "does/not/exist.toml: no such file"),
        ([str(SCENARIOS / "lee_kim_shim.toml"), "--set", "network.graph.kind=rnig"],
         "network.graph: unknown kind 'rnig'; expected one of ring, complete, edges, cells, attachment"),
        ([str(SCENARIOS / "lee_kim_shim.toml"), "--set", "estimator.q=2"], "estimator.q: the sensor set is not 4-redundantly observable"),
        ([str(SCENARIOS / "lee_kim_shim.toml"), "--set", "estimator.bogus=1"], "estimator.bogus: unknown key"),
    ],
)
def test_bad_input_exits_2_with_a_message(run_rse, tmp_path, args, message):
    res = run_rse("simulate", *args, "--out", str(tmp_path / "r"), "--no-progress")
    assert res.returncode == 2
    no_traceback(res)
    assert message in " ".join(res.stderr.split())


def test_toml_syntax_error_exits_2(run_rse, tmp_path):
    p = tmp_path / "broken.toml"
    p.write_text("[run]\nname = \n")
    res = run_rse("simulate", str(p), "--no-progress")
    assert res.returncode == 2
    no_traceback(res)
    assert "broken.toml: TOML syntax error" in res.stderr


def test_check_reports_conditions(run_rse):
    res = run_rse("check", str(SCENARIOS / "lee_kim_shim.toml"))
    assert res.returncode == 0, res.stdout + res.stderr
    out = " ".join(res.stdout.split())
    for text in ("2-redundant observability, q = 1 (Assumption 2)", "common basis (Assumption 4)",
                 "network connected (Assumption 3)", "lambda_2(L)", "1.38197", "Theorem 1 bound",
                 "Theorem 3 steady-state bound"):
        assert text in out
    assert "FAILS" not in out


def test_check_exits_1_when_a_condition_fails(run_rse):
    res = run_rse("check", str(SCENARIOS / "lee_kim_shim.toml"), "--set", "estimator.q=2")
    assert res.returncode == 1
    no_traceback(res)
    assert "FAILS" in res.stdout


def test_bench_prints_agent_rounds_per_second(run_rse):
    res = run_rse("bench", "simulate", str(SCENARIOS / "lee_kim_shim.toml"), "--set", "run.duration=5", "--set", "expect=[]", "--repeat", "1")
    assert res.returncode == 0, res.stderr
    assert "simulator agent-rounds/s" in res.stdout


@pytest.mark.skipif(not __import__("sys").platform.startswith("linux"), reason="reads /proc")
def test_bench_start_of_the_command_lies_between_its_launch_and_its_first_line():
    # rse bench run's start-up figure counts from this; psutil's create_time read up to 1 s early
    import subprocess
    import sys
    import time

    code = ("import time; now = time.time(); from agents.cli.bench import _command_started; "
            "print(_command_started(), now)")
    before = time.time()
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    started, first_line = map(float, out.split())
    assert before - 0.011 <= started <= first_line  # clock ticks of 10 ms, rounded down
