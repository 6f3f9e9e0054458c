"""``rse certs`` and the access-control rules of ``--secure`` (no network)."""

from __future__ import annotations

import ipaddress
import stat

import pytest
from click.testing import CliRunner

from agents.cli import cli
from tests.conftest import SCENARIOS

x509 = pytest.importorskip("cryptography.x509", reason="rse certs needs the cryptography package (pip install '.[secure]')")


def _load(path):
    return x509.load_pem_x509_certificate(path.read_bytes())


def test_certs_for_a_scenario_one_identity_per_process(tmp_path):
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    d = tmp_path / "certs"
    r = CliRunner().invoke(cli, ["certs", str(d), "--scenario", str(SCENARIOS / "lee_kim_shim.toml"),
                                 "--host", "10.0.0.5", "--host", "router.example.org"])
    assert r.exit_code == 0, r.output
    idents = ["router", "plant", "monitor", *(f"agent-{i}" for i in range(1, 6))]
    signing = [f"{i}.sig.{ext}" for i in idents if i != "router" for ext in ("key", "pub")]  # Ed25519, not the router's
    assert {p.name for p in d.iterdir()} == {"ca.pem", *(f"{i}.pem" for i in idents), *(f"{i}.key" for i in idents),
                                             *signing}
    ca = _load(d / "ca.pem")
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    for ident in idents:
        cert = _load(d / f"{ident}.pem")
        assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == ident
        cert.verify_directly_issued_by(ca)  # raises if not signed by this CA
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        assert {"localhost", "router.example.org", ident} <= set(san.get_values_for_type(x509.DNSName))
        assert {ipaddress.ip_address("127.0.0.1"), ipaddress.ip_address("10.0.0.5")} <= \
            set(san.get_values_for_type(x509.IPAddress))
        eku = cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
        assert {ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH} <= set(eku)
        key_path = d / f"{ident}.key"
        assert stat.S_IMODE(key_path.stat().st_mode) == 0o600
        key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
        assert isinstance(key, ec.EllipticCurvePrivateKey)
        assert key.public_key().public_numbers() == cert.public_key().public_numbers()


def test_certs_errors_are_one_line_exit_2(tmp_path):
    run = CliRunner().invoke
    d = tmp_path / "c"
    assert run(cli, ["certs", str(d), "--agents", "2"]).exit_code == 0
    cases = [
        (["certs", str(d), "--agents", "2"], "already holds a certificate set"),
        (["certs", str(tmp_path / "x")], "exactly one of --scenario"),
        (["certs", str(tmp_path / "x"), "--agents", "2", "--scenario", str(SCENARIOS / "lee_kim_shim.toml")],
         "exactly one of --scenario"),
        (["certs", str(tmp_path / "x"), "--agents", "2", "--host", "no such host"], "invalid host"),
        (["certs", str(d / "ca.pem" / "sub"), "--agents", "2"], "cannot write certificates to"),
    ]
    for args, words in cases:
        r = run(cli, args)
        assert r.exit_code == 2, (args, r.output)
        assert words in r.output and "Traceback" not in r.output, (args, r.output)
    first = (d / "ca.pem").read_bytes()
    assert run(cli, ["certs", str(d), "--agents", "3", "--force"]).exit_code == 0
    assert (d / "ca.pem").read_bytes() != first and (d / "agent-3.key").is_file()


def test_access_control_rules_per_identity():
    from transport.secure import access_control, agent_ids_in, identity_for, secure_endpoint, validate_identity

    acl = access_control([3, 1], run_id="r1")
    assert acl["enabled"] and acl["default_permission"] == "deny"
    assert [s["cert_common_names"] for s in acl["subjects"]] == [["plant"], ["monitor"], ["agent-1"], ["agent-3"]]
    rules = {r["id"]: r for r in acl["rules"]}
    pol = {p["subjects"][0]: [rules[i] for i in p["rules"]] for p in acl["policies"]}

    def allowed(who, message, flow):
        return {k for r in pol[who] if message in r["messages"] and flow in r["flows"] for k in r["key_exprs"]}

    assert allowed("agent-3", "put", "ingress") == {"rse/r1/agent/3/**", "rse/r1/ctl/*/3"}
    assert allowed("agent-3", "liveliness_token", "ingress") == {"rse/r1/alive/agent/3"}
    assert "rse/r1/plant/truth" not in allowed("agent-3", "put", "egress") | allowed("agent-3", "declare_subscriber", "ingress")
    assert allowed("monitor", "put", "egress") == {"rse/r1/plant/truth", "rse/r1/ctl/**"}
    assert allowed("plant", "put", "ingress") == {"rse/r1/plant/**", "rse/r1/ctl/*/plant"}
    assert access_control([1])["rules"][0]["key_exprs"][0].startswith("rse/*/")
    with pytest.raises(ValueError):
        access_control([1], run_id="a/b")
    assert identity_for("agent", 7) == "agent-7" and identity_for("monitor") == "monitor"
    for bad in ("agent-07", "agent-", "root", "../plant", "agent-1/x"):
        with pytest.raises(ValueError):
            validate_identity(bad)
    assert secure_endpoint("tcp/router:7447") == "tls/router:7447" and secure_endpoint("tls/h:1") == "tls/h:1"
    with pytest.raises(ValueError):
        secure_endpoint("udp/h:1")
    assert agent_ids_in(SCENARIOS) == []


def test_router_admits_the_agents_of_its_certificate_directory(tmp_path):
    from agents.net.router import router_config
    from estimation.errors import ScenarioError
    from transport.certs import write_certs
    from transport.secure import tls_files

    write_certs(tmp_path, ["router", "plant", "monitor", "agent-2", "agent-5"])
    conf, eps = router_config(["tcp/127.0.0.1:0"], secure=tls_files(tmp_path, "router"))
    assert eps[0].startswith("tls/127.0.0.1:") and not eps[0].endswith(":0")
    import json

    acl = json.loads(str(conf))["access_control"]
    assert [s["id"] for s in acl["subjects"]] == ["plant", "monitor", "agent-2", "agent-5"]
    (tmp_path / "agent-2.pem").unlink()
    (tmp_path / "agent-5.pem").unlink()
    with pytest.raises(ScenarioError, match="no agent-"):
        router_config(["tcp/127.0.0.1:0"], secure=tls_files(tmp_path, "router"))
