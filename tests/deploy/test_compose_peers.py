"""``rse compose --secure DIR --peers``: a compose file of secure peers, no router; its
content, and its services' commands run as local processes (no Docker here)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.deploy.conftest import rse_cmd
from tests.deploy.test_compose import LKS, SMALL, _free_port, _materialize, agent_ids, compose, load

pytest.importorskip("yaml", reason="rse compose needs PyYAML")
pytest.importorskip("cryptography", reason="rse certs needs the cryptography package (pip install '.[secure]')")


@pytest.fixture(scope="module")
def certs(tmp_path_factory) -> Path:
    from transport.certs import write_certs

    d = tmp_path_factory.mktemp("certs")
    write_certs(d, ["plant", "monitor", *(f"agent-{i}" for i in agent_ids(LKS))])
    return d


def _peers_file(run_rse, certs: Path, out: Path) -> dict:
    args = [a for s in SMALL for a in ("--set", s)]
    res = compose(run_rse, str(LKS), "-o", str(out), "--secure", str(certs), "--peers", "--run-id", "p2p", *args)
    assert res.returncode == 0 and "no router (secure peers)" in res.stdout, res.stderr
    return load(out)


def test_a_compose_file_of_secure_peers_names_no_router(run_rse, certs, tmp_path):
    """No router service; every process listens on tls/0.0.0.0:7450, links to each later
    service by name (each pair once), presents its own identity and mounts ca.pem, its own
    certificate and key and the team's certificates, no other key; it waits for team only,
    whose command writes a team of peers. --peers without --secure is a one-line error."""
    spec = _peers_file(run_rse, certs, tmp_path / "compose.yml")
    names = ["plant", "monitor", *(f"agent-{i}" for i in agent_ids(LKS))]
    assert "router" not in spec["services"] and set(spec["services"]) == {"team", *names}
    assert spec["services"]["team"]["command"][-1] == "--peers"
    for n, name in enumerate(names):
        svc = spec["services"][name]
        cmd = svc["command"]
        assert "--client" not in cmd and cmd[cmd.index("--listen") + 1] == "tls/0.0.0.0:7450", cmd
        assert [cmd[i + 1] for i, a in enumerate(cmd) if a == "--connect"] == [f"tls/{o}:7450" for o in names[n + 1:]]
        assert cmd[cmd.index("--secure") + 1] == "/certs" and cmd[cmd.index("--identity") + 1] == name
        mounted = sorted(v.split(":")[1].removeprefix("/certs/") for v in svc["volumes"] if ":/certs/" in v)
        assert mounted == sorted(["ca.pem", f"{name}.key", *(f"{o}.pem" for o in names)]), mounted
        assert set(svc["depends_on"]) == {"team"}
    res = run_rse("compose", str(LKS), "-o", str(tmp_path / "x.yml"), "--peers")
    assert res.returncode == 2 and "--peers is a team of secure peers: give --secure DIR too" in res.stderr


@pytest.mark.slow
@pytest.mark.multiprocess
def test_a_compose_file_of_secure_peers_runs(run_rse, procs, certs, tmp_path):
    """Its services' commands as local processes, each in a directory holding only its
    mounts, the service names and port 7450 mapped to loopback ports: the team runs to the
    end with nothing rejected."""
    spec = _peers_file(run_rse, certs, tmp_path / "deploy" / "compose.yml")
    root = tmp_path / "containers"
    root.mkdir()
    dirs = {name: _materialize(name, svc, tmp_path / "deploy", root) for name, svc in spec["services"].items()}
    ports = {name: _free_port() for name in spec["services"]}

    def local(cmd: list[str], name: str) -> list[str]:
        out = []
        for a in cmd:
            if a.startswith(("/scenario", "/certs", "/runs", "/team")):
                a = str(dirs[name] / a.lstrip("/"))
            elif a == "tls/0.0.0.0:7450":
                a = f"tls/127.0.0.1:{ports[name]}"
            elif a.startswith("tls/") and a.endswith(":7450"):
                a = f"tls/127.0.0.1:{ports[a[4:-5]]}"
            out.append(a)
        return out

    team = procs.start(rse_cmd(*local(spec["services"]["team"]["command"], "team")))
    assert team.wait(timeout=120) == 0, team.communicate()[1]
    run = {name: procs.start(rse_cmd(*local(svc["command"], name))) for name, svc in spec["services"].items()
           if name not in ("team", "monitor")}
    mon_cmd = local(spec["services"]["monitor"]["command"], "monitor")
    for flag in ("--web-port", "--grpc-port"):  # no viewer here
        i = mon_cmd.index(flag)
        del mon_cmd[i:i + 2]
    run["monitor"] = procs.start(rse_cmd(*(a for a in mon_cmd if a != "--serve-web"), "--no-rerun"))
    errs = {name: p.communicate(timeout=300)[1] for name, p in run.items()}  # a hang only
    for name, p in run.items():
        assert p.returncode == 0 and "Traceback" not in errs[name], errs
    summary = json.loads((dirs["monitor"] / "runs" / "p2p" / "summary.json").read_text())
    assert summary["rounds"] == 600 and summary["complete"] and summary["rejected"] == {}, summary["rejected"]
