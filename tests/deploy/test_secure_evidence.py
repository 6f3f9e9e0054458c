"""Equivocation becomes evidence in a networked team (``rse run --sign DIR``), with real
processes: agents sign their estimates, the regular receivers tell the monitor what they
were told, and the monitor convicts on two valid signed copies that differ
(:mod:`agents.net.evidence_net`)."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from tests.agents.test_evidence import BYZ, _edits
from tests.conftest import SCENARIOS
from tests.deploy.conftest import Procs, rse_cmd

pytest.importorskip("cryptography", reason="signatures need the cryptography package (pip install '.[secure]')")

pytestmark = pytest.mark.multiprocess

MITRA = SCENARIOS / "mitra_cells.toml"


@pytest.fixture(scope="module")
def keys(tmp_path_factory) -> Path:
    from transport.certs import write_certs

    d = tmp_path_factory.mktemp("keys")
    write_certs(d, ["plant", "monitor", *(f"agent-{i}" for i in range(1, 17))])
    return d


def _overrides(start: int) -> list[str]:
    return [f'attacks=[{{target="agent", agents=[{BYZ}], kind="equivocation", start={start}}}]', "run.rounds=40",
            "expect=[]"]


def _run(args: list[str]) -> tuple[int, str, str]:
    ps = Procs()
    try:
        p = ps.start(rse_cmd(*args))
        so, se = p.communicate(timeout=600)  # a hang only
        return p.returncode, so, se
    finally:
        ps.kill_all()


@pytest.mark.slow
def test_a_networked_equivocator_is_convicted_within_2_rounds(keys, tmp_path):
    """mitra_cells.toml in lockstep, agent 5 equivocating from a round that differs per seed,
    plain peers and secure peers: agent 5 and nobody else is convicted within 2 rounds of
    its first equivocation, the one record verifies offline and every edit of it fails, the
    estimates equal rse simulate's (signing changes no value), the dashboard marks the
    conviction, and rse verify-evidence accepts the file and rejects an edited copy."""
    from agents.api import load_experiment
    from agents.cli import cli
    from agents.evidence import verify_file, verify_record
    from agents.simulate import simulate
    from transport.signing import load_public_keys

    pub = load_public_keys(keys)
    for seed, secure in ((0, True), (1, False)):  # 10 seeds: docs/deployment.md
        start = 5 + 4 * seed
        out = tmp_path / f"run{seed}"
        args = ["run", str(MITRA), "--sign", str(keys), "--seed", str(seed), "--out", str(out), "--no-progress",
                "--save-estimates", "--deadline", "30", *(["--no-rerun"] if secure else [])]  # a recording: plain
        for ov in _overrides(start):
            args += ["--set", ov]
        code, so, se = _run(args + (["--secure", str(keys)] if secure else []))
        assert code == 0 and "Traceback" not in se, se
        ev = json.loads((out / "summary.json").read_text())["evidence"]
        print(f"\nseed {seed} ({'secure' if secure else 'plain'} peers): equivocation from round {start}, {ev}")
        assert set(ev["convicted"]) == {str(BYZ)}, ev
        k = ev["convicted"][str(BYZ)]
        assert start <= k <= start + 2 and ev["bad_signatures"] == 0 and ev["verifications"] == 2, ev
        assert f"convicted: agent {BYZ} (round {k})" in " ".join(so.split()), so
        checked = verify_file(out / "evidence.jsonl", pub)
        assert [(n, why) for n, _rec, why in checked] == [(1, None)], checked
        rec = checked[0][1]
        assert rec is not None and rec["stamp"] == start and rec["sender"] == BYZ and rec["convicted_at"] == k
        for what, edit in _edits().items():
            bad = copy.deepcopy(rec)
            edit(bad)
            assert verify_record(bad, pub) is not None, what
        exp, _ = load_experiment(MITRA, tuple(_overrides(start)), seed)
        ref = simulate(exp, keep_trajectories=True)
        assert float(np.max(np.abs(np.load(out / "estimates.npy") - ref.estimates))) == 0.0
    _dashboard_marks(out / "recording.rrd", k)
    ok = CliRunner().invoke(cli, ["verify-evidence", str(out / "evidence.jsonl"), "--certs", str(keys)])
    assert ok.exit_code == 0 and f"verified: agent {BYZ} equivocated at stamp {start}" in ok.output, ok.output
    rec["messages"][1]["x"][0] += 1.0
    edited = tmp_path / "edited.jsonl"
    edited.write_text(json.dumps(rec) + "\n")
    bad = CliRunner().invoke(cli, ["verify-evidence", str(edited), "--certs", str(keys)])
    assert bad.exit_code == 1 and "line 1: message 2: the signature does not verify" in bad.output, bad.output


def _dashboard_marks(rrd: Path, k: int) -> None:
    """The monitor's recording marks the conviction at its round (as rse simulate's does)."""
    try:
        import datafusion  # noqa: F401  (reading .rrd files needs rerun-sdk[catalog], the test extra)
        import rerun  # noqa: F401
    except ImportError:
        return
    from tests.agents.test_dashboard import read_rrd, rows

    text = rows(read_rrd(rrd), "/events/convictions:TextLog:text")
    assert [int(x) for x in text["k"]] == [k]
    assert f"agent {BYZ} convicted of equivocation" in str(text.iloc[0, 1])


def test_sign_names_a_directory_without_keys(tmp_path):
    code, _so, se = _run(["run", str(MITRA), "--sign", str(tmp_path), "--no-rerun"])
    assert code == 2 and "--sign" in se and "no *.sig.pub signing keys" in se and "Traceback" not in se, se
