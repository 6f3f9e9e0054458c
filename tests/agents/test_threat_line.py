"""The one-line warning of `rse check`, `rse simulate` and `rse run` when a scenario's own
attacks exceed the threat model its algorithm tolerates (agents/threat.py)."""

from __future__ import annotations

import pytest

import rse
from tests.conftest import SCENARIOS, scenario_params

TWO_BANKS = 'attacks=[{target="sensor", sensors=[1, 2], kind="constant", value=1.0}]'
TWO_BYZANTINE = 'attacks=[{target="agent", agents=[5, 6], kind="cancellation"}]'
LKS = SCENARIOS / "lee_kim_shim.toml"


def _invoke(*args: str) -> tuple[int, str]:
    from click.testing import CliRunner

    from agents.cli import cli

    res = CliRunner().invoke(cli, list(args))
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    return res.exit_code, res.output


def test_two_attacked_banks_exceed_lee_kim_shims_q_of_one():
    exp = rse.load(LKS, set=[TWO_BANKS, "run.duration=0.1"])
    line = rse.beyond_threat_model(exp)
    assert line is not None and "\n" not in line
    assert "2 sensor banks attacked (1, 2)" in line and "estimator.q = 1" in line


def test_one_attacked_bank_is_within_q_of_one():
    assert rse.beyond_threat_model(rse.load(LKS, set=["run.duration=0.1"])) is None
    exp = rse.load(LKS, set=["run.duration=0.1", "estimator.q=2", TWO_BANKS], check_conditions=False)
    assert rse.beyond_threat_model(exp) is None


def test_two_byzantine_neighbours_exceed_lfres_f_of_one():
    exp = rse.load(SCENARIOS / "mitra_cells.toml", set=[TWO_BYZANTINE], check_conditions=False)
    line = rse.beyond_threat_model(exp)
    assert line is not None and "2 Byzantine in-neighbours" in line and "estimator.f = 1" in line


def test_a_sensor_attack_is_outside_lfres_model_of_trusted_sensors():
    exp = rse.load(SCENARIOS / "mitra_cells.toml", check_conditions=False,
                   set=['attacks=[{target="sensor", sensors=[1], kind="constant", value=1.0}]'])
    assert "assumes trusted sensors" in (rse.beyond_threat_model(exp) or "")


# every paper scenario whose algorithm declares a budget (Ugrinovskii's declares none: not judged)
@pytest.mark.parametrize("path", scenario_params(sorted(p for p in SCENARIOS.glob("*.toml") if "ugrinovskii" not in p.name)))
def test_no_paper_scenario_is_beyond_its_threat_model(path):
    assert rse.beyond_threat_model(rse.load(path, check_conditions=False)) is None


def test_rse_check_and_simulate_print_the_line_once(tmp_path):
    for args in (["check", str(LKS)],
                 ["simulate", str(LKS), "--no-progress", "--no-rerun", "--out", str(tmp_path / "r")]):
        code, out = _invoke(*args, "--set", TWO_BANKS, "--set", "run.duration=0.2")
        assert out.count("attacks beyond the threat model") == 1, out
        assert code in (0, 1, 3), out
    code, out = _invoke("check", str(LKS), "--set", "run.duration=0.2")
    assert "threat model" not in out


def test_rse_run_prints_the_line_before_it_starts_the_team(tmp_path, monkeypatch):
    import agents.net.launcher as launcher

    def stop(*args, **kwargs):  # the processes themselves are not what is tested here
        raise KeyboardInterrupt

    monkeypatch.setattr(launcher, "launch", stop)
    code, out = _invoke("run", str(LKS), "--set", TWO_BANKS, "--no-progress", "--no-rerun", "--out", str(tmp_path / "r"))
    assert code == 130 and out.count("attacks beyond the threat model") == 1, out
