"""``rse compose --dask-workers N``: a Dask scheduler and N workers beside the team, for
``rse sweep --cluster`` (docs/sweeps.md)."""

from __future__ import annotations

import yaml

from tests.conftest import SCENARIOS

MITRA = SCENARIOS / "mitra_cells.toml"


def test_dask_workers_adds_a_scheduler_and_n_single_threaded_workers(run_rse, tmp_path):
    res = run_rse("compose", str(MITRA), "-o", str(tmp_path / "compose.yml"), "--dask-workers", "3")
    assert res.returncode == 0, res.stderr
    assert "Dask scheduler and 3 worker(s)" in res.stdout
    text = (tmp_path / "compose.yml").read_text()
    assert "--dask-workers 3" in text  # the regenerating command in the header
    services = yaml.safe_load(text)["services"]
    sched, worker = services["dask-scheduler"], services["dask-worker"]
    assert sched["entrypoint"] == ["dask", "scheduler"] and sched["ports"] == ["8786:8786"]
    assert sched["command"][sched["command"].index("--port") + 1] == "8786"
    assert worker["entrypoint"] == ["dask", "worker"] and worker["command"][0] == "tcp://dask-scheduler:8786"
    assert worker["command"][worker["command"].index("--nthreads") + 1] == "1"
    assert worker["deploy"]["replicas"] == 3 and worker["depends_on"] == ["dask-scheduler"]
    assert worker["environment"]["OPENBLAS_NUM_THREADS"] == "1"
    assert "volumes" not in worker  # tasks carry their scenario: workers mount nothing
    assert sched["image"] == worker["image"] == services["team"]["image"]  # the full image (cluster extra), as the team service
    # the team's services are unchanged
    plain = tmp_path / "plain.yml"
    assert run_rse("compose", str(MITRA), "-o", str(plain)).returncode == 0
    team = yaml.safe_load(plain.read_text())["services"]
    assert {k: v for k, v in services.items() if not k.startswith("dask-")} == team


def test_dask_workers_zero_adds_nothing_and_negative_is_refused(run_rse, tmp_path):
    res = run_rse("compose", str(MITRA), "-o", "-", "--dask-workers", "0")
    assert res.returncode == 0 and "dask-scheduler" not in res.stdout
    res = run_rse("compose", str(MITRA), "-o", "-", "--dask-workers", "-1")
    assert res.returncode == 2 and "Traceback" not in res.stderr
