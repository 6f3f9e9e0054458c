"""Equivocation becomes evidence (agents/evidence.py, transport/signing.py, rse verify-evidence).

mitra_cells.toml in the lockstep simulator with agent 5 equivocating (a different signed
value to each receiver) from a round that differs per seed: convicted within 2 rounds of
its first equivocation, no regular agent convicted, every record verifies offline with the
team's public keys, and an edited record fails.
"""

from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from tests.conftest import SCENARIOS

pytest.importorskip("cryptography", reason="signatures need the cryptography package (pip install '.[secure]')")

MITRA = SCENARIOS / "mitra_cells.toml"
BYZ = 5


@pytest.fixture(scope="module")
def keys(tmp_path_factory) -> Path:
    from transport.certs import write_certs

    d = tmp_path_factory.mktemp("keys")
    write_certs(d, ["plant", "monitor", *(f"agent-{i}" for i in range(1, 17))])
    return d


def _equivocating(start: int) -> tuple[str, ...]:
    return (f'attacks=[{{target="agent", agents=[{BYZ}], kind="equivocation", start={start}}}]', "run.rounds=60",
            "expect=[]")


def _edits() -> dict:
    return {
        "a value": lambda r: r["messages"][0]["x"].__setitem__(0, r["messages"][0]["x"][0] + 1e-9),
        "a signature": lambda r: r["messages"][1].__setitem__("signature", r["messages"][0]["signature"]),
        "the stamp": lambda r: r.__setitem__("stamp", r["stamp"] - 1),
        "the sender": lambda r: r.update(sender=4, identity="agent-4"),
        "the run": lambda r: r.__setitem__("run", "another-run"),
        "one message twice": lambda r: r["messages"].__setitem__(1, copy.deepcopy(r["messages"][0])),
    }


def test_the_equivocating_agent_is_convicted_within_2_rounds_over_10_seeds(keys):
    from agents.api import load_experiment
    from agents.evidence import verify_record, watch_for
    from agents.simulate import simulate
    from transport.signing import load_public_keys

    pub = load_public_keys(keys)
    for seed in range(10):
        start = 5 + 4 * seed
        exp, _ = load_experiment(MITRA, _equivocating(start), seed)
        w = watch_for(exp, keys, f"eq-{seed}")
        simulate(exp, evidence=w, record=False)
        assert w.convicted == {BYZ: start + 1}, (seed, w.convicted)  # within 2 rounds: start + 2 at most
        assert w.bad_signatures == 0 and len(w.records) == 1
        rec = w.records[0]
        assert rec["stamp"] == start and rec["sender"] == BYZ
        assert verify_record(json.loads(json.dumps(rec)), pub) is None
        for what, edit in _edits().items():
            bad = copy.deepcopy(rec)
            edit(bad)
            assert verify_record(bad, pub) is not None, what
        # signatures: one per broadcast and per addressed message; verifications only on the conflict
        assert w.verifications <= len(exp.agent_ids)


def test_regular_agents_alone_are_never_convicted(keys):
    """Agent 5 sending one false value to everyone (constant): a lie, not an equivocation."""
    from agents.api import load_experiment
    from agents.evidence import watch_for
    from agents.simulate import simulate

    exp, _ = load_experiment(MITRA, (f'attacks=[{{target="agent", agents=[{BYZ}], kind="constant", value=7.0}}]',
                                     "run.rounds=60", "expect=[]"), 0)
    w = watch_for(exp, keys, "honest")
    simulate(exp, evidence=w, record=False)
    assert w.convicted == {} and w.records == [] and w.verifications == 0


def test_rse_simulate_sign_and_rse_verify_evidence(keys, tmp_path):
    """The CLI: rse simulate --sign writes evidence.jsonl and the summary's convicted agents;
    rse verify-evidence accepts it (exit 0) and rejects an edited copy (exit 1, the line named)."""
    from agents.cli import cli

    out = tmp_path / "run"
    args = ["simulate", str(MITRA), "--sign", str(keys), "--out", str(out), "--no-rerun", "--no-progress"]
    for ov in _equivocating(20):
        args += ["--set", ov]
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 0, r.output
    assert f"convicted: agent {BYZ} (round 21)" in r.output
    assert json.loads((out / "summary.json").read_text())["evidence"]["convicted"] == {str(BYZ): 21}
    ok = CliRunner().invoke(cli, ["verify-evidence", str(out / "evidence.jsonl"), "--certs", str(keys)])
    assert ok.exit_code == 0 and "verified: agent 5 equivocated at stamp 20" in ok.output, ok.output
    rec = json.loads((out / "evidence.jsonl").read_text())
    rec["messages"][0]["x"][0] += 1.0
    edited = tmp_path / "edited.jsonl"
    edited.write_text(json.dumps(rec) + "\n")
    bad = CliRunner().invoke(cli, ["verify-evidence", str(edited), "--certs", str(keys)])
    assert bad.exit_code == 1 and "line 1: message 1: the signature does not verify" in bad.output, bad.output
    assert "Traceback" not in bad.output
    missing = CliRunner().invoke(cli, ["verify-evidence", str(edited), "--certs", str(tmp_path / "none")])
    assert missing.exit_code == 2 and "no such directory" in missing.output


def test_signing_keys_are_private_and_bind_every_field(keys):
    import stat

    from transport.signing import load_public_keys, load_signer, payload_bytes, verify

    assert stat.S_IMODE((keys / "agent-3.sig.key").stat().st_mode) == 0o600
    assert not (keys / "router.sig.key").exists()  # the router signs nothing
    s, pub = load_signer(keys, "agent-3"), load_public_keys(keys)["agent-3"]
    p = payload_bytes([1.0, 2.0])
    sig = s.sign("r", "est", 3, None, 7, p)
    assert verify(pub, sig, "r", "est", 3, None, 7, p)
    for args in [("r2", "est", 3, None, 7, p), ("r", "done", 3, None, 7, p), ("r", "est", 4, None, 7, p),
                 ("r", "est", 3, 1, 7, p), ("r", "est", 3, None, 8, p), ("r", "est", 3, None, 7, payload_bytes([1.0, 2.5]))]:
        assert not verify(pub, sig, *args), args


def test_the_dashboard_marks_the_conviction(keys, tmp_path):
    pytest.importorskip("rerun")
    pytest.importorskip("datafusion", reason="reading .rrd files needs rerun-sdk[catalog] (the test extra)")
    from agents.cli import cli
    from tests.agents.test_dashboard import read_rrd, rows

    out = tmp_path / "run"
    args = ["simulate", str(MITRA), "--sign", str(keys), "--out", str(out), "--no-progress"]
    for ov in _equivocating(12):
        args += ["--set", ov]
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 0, r.output
    text = rows(read_rrd(out / "recording.rrd"), "/events/convictions:TextLog:text")
    assert [int(k) for k in text["k"]] == [13]
    assert "agent 5 convicted of equivocation" in str(text.iloc[0, 1])
