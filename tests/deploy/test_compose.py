"""``rse compose``, the Dockerfile and the container health check.

Structural tests of the generated compose file (services, router clients, mounts, run id,
ports, per-service credentials, bad input), the committed docker-compose.yml against a
fresh generation, ``docker-compose config`` on generated files (skipped where neither
``docker-compose`` nor ``docker compose`` is installed), the Dockerfile's instructions,
``python -m agents.healthcheck`` against real sockets, and a *compose run without Docker*:
every service's command of a generated secure file run as a local process that sees only
what the service mounts (its own credentials, the scenario), the router's host name and
the published ports mapped to loopback.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
import tomllib
import urllib.request
from pathlib import Path

import pytest
import yaml

from tests.conftest import ROOT, SCENARIOS
from tests.deploy.conftest import rse_cmd

MITRA = SCENARIOS / "mitra_cells.toml"
LKS = SCENARIOS / "lee_kim_shim.toml"
ROLES = ("plant", "monitor")


def compose(run_rse, *args: str, cwd: Path | None = None):
    res = run_rse("compose", *args, cwd=cwd)
    assert "Traceback" not in res.stderr + res.stdout
    return res


def load(path: Path) -> dict:
    return yaml.safe_load(path.read_text())


def agent_ids(scenario: Path) -> list[int]:
    from agents.api import load_experiment

    exp, _ = load_experiment(scenario, (), None)
    return list(exp.agent_ids)


def fake_certs(d: Path, ids) -> Path:
    """The file names `rse certs` writes (rse compose only checks they exist)."""
    d.mkdir(parents=True, exist_ok=True)
    for name in ["ca.pem", *(f"{who}.{ext}" for who in ["router", "plant", "monitor", *(f"agent-{i}" for i in ids)]
                             for ext in ("pem", "key"))]:
        (d / name).write_text(f"{name}\n")
    return d


def flag(command: list[str], name: str) -> str:
    """The value after ``name`` in a command (asserting it occurs exactly once)."""
    assert command.count(name) == 1, (name, command)
    return command[command.index(name) + 1]


@pytest.fixture(scope="module")
def mitra(tmp_path_factory) -> tuple[dict, Path]:
    """rse compose of mitra_cells.toml with a run id, written next to a copy of the scenario."""
    from tests.conftest import rse

    d = tmp_path_factory.mktemp("plain")
    res = rse("compose", str(MITRA), "-o", str(d / "out" / "compose.yml"), "--run-id", "team-7")
    assert res.returncode == 0, res.stderr
    assert "16 agent(s)" in res.stdout and "run id team-7" in res.stdout
    return load(d / "out" / "compose.yml"), d / "out" / "compose.yml"


@pytest.fixture(scope="module")
def secure(tmp_path_factory) -> tuple[dict, Path, Path]:
    from tests.conftest import rse

    d = tmp_path_factory.mktemp("secure")
    certs = fake_certs(d / "certs", agent_ids(MITRA))
    res = rse("compose", str(MITRA), "-o", str(d / "compose.yml"), "--secure", str(certs))
    assert res.returncode == 0, res.stderr
    return load(d / "compose.yml"), d / "compose.yml", certs


# ------------------------------------------------------------------ structure


def test_one_service_per_process_of_the_team(mitra):
    spec, _ = mitra
    ids = agent_ids(MITRA)
    assert len(ids) == 16
    assert set(spec["services"]) == {"router", "team", "plant", "monitor", *(f"agent-{i}" for i in ids)}
    for i in ids:
        cmd = spec["services"][f"agent-{i}"]["command"]
        assert cmd[0] == "agent" and flag(cmd, "--id") == str(i)
    assert spec["services"]["plant"]["command"][0] == "plant"
    assert spec["services"]["monitor"]["command"][0] == "monitor"
    images = {name: svc["image"] for name, svc in spec["services"].items()}
    slim = {"router", "plant", *(f"agent-{i}" for i in ids)}  # the Dockerfile's target agent
    assert {images[n] for n in slim} == {"resilient-state-estimation-agent:latest"}
    assert images["monitor"] == "resilient-state-estimation-monitor:latest"
    assert images["team"] == "resilient-state-estimation:latest"  # the offline design: the full image


def test_the_design_runs_once_and_each_process_reads_only_its_slice(mitra):
    """The one-shot service team writes team.json and the slices to the volume team; the
    plant, the monitor and the agents wait for it to complete and start from their slice
    (no scenario, no design)."""
    spec, _ = mitra
    team = spec["services"]["team"]
    cmd = team["command"]
    assert cmd[:2] == ["compose", "/scenario/mitra_cells.toml"] and flag(cmd, "--write-team") == "/runs"
    assert flag(cmd, "--run-id") == "team-7"
    assert "team:/runs" in team["volumes"] and team["restart"] == "no"
    assert spec["volumes"] == {"runs": {}, "team": {}}
    for name, svc in spec["services"].items():
        if name in ("router", "team"):
            continue
        assert svc["depends_on"] == {"router": {"condition": "service_healthy"},
                                     "team": {"condition": "service_completed_successfully"}}, name
        assert svc["volumes"] == ["team:/team:ro"] + (["runs:/runs"] if name == "monitor" else []), name
        assert flag(svc["command"], "--team") == "/team/team.json"
        assert "--set" not in svc["command"] and not any(a.startswith("/scenario") for a in svc["command"])


def test_write_team_writes_what_rse_agent_plant_and_monitor_team_read(run_rse, tmp_path):
    res = compose(run_rse, str(LKS), "--run-id", "lks-9", "--write-team", str(tmp_path / "t"))
    assert res.returncode == 0, res.stderr
    team = json.loads((tmp_path / "t" / "team.json").read_text())
    assert team["run_id"] == "lks-9" and team["transport"] == "client" and team["connect"] == ["tcp/router:7447"]
    import pickle

    from agents.net.slices import PlantSlice, find_slices, read_slices

    for i in agent_ids(LKS):
        data = find_slices(tmp_path / "t" / "team", [i])
        assert data is not None and [s.agent_id for s in read_slices(data)] == [i]
    plant = pickle.loads((tmp_path / "t" / "team" / "plant.pkl").read_bytes())
    assert isinstance(plant, PlantSlice) and plant.agent_ids == agent_ids(LKS)
    exp = pickle.loads((tmp_path / "t" / "team" / "experiment.pkl").read_bytes())
    assert exp.agent_ids == agent_ids(LKS) and exp.scenario.run.name == "lee_kim_shim"


def test_every_process_is_a_client_of_the_router_and_waits_for_it(mitra):
    spec, _ = mitra
    router = spec["services"]["router"]
    assert router["command"][:3] == ["router", "--listen", "tcp/0.0.0.0:7447"]
    assert router["ports"] == ["7447:7447"]
    assert router["healthcheck"]["test"] == ["CMD", "python", "-m", "agents.healthcheck"]
    for name, svc in spec["services"].items():
        assert svc.get("init") is True, name  # signals forwarded, zombies reaped
        if name in ("router", "team"):
            continue
        cmd = svc["command"]
        assert "--client" in cmd and flag(cmd, "--connect") == "tcp/router:7447", name
        assert "--listen" not in cmd
        assert svc["depends_on"]["router"] == {"condition": "service_healthy"}, name


def test_the_scenario_is_mounted_read_only_and_read_from_the_mount(mitra):
    """Only the service team, which builds the experiment, reads the scenario file."""
    spec, path = mitra
    for name, svc in spec["services"].items():
        if name == "router":
            assert "volumes" not in svc  # plain: the router reads no file
            continue
        if name != "team":
            assert not [v for v in svc["volumes"] if v.split(":")[1].startswith("/scenario")], name  # its slice only
            assert not any(a.startswith("/scenario") for a in svc["command"]), name
            continue
        mounts = [v for v in svc["volumes"] if v.split(":")[1] == "/scenario/mitra_cells.toml"]
        assert len(mounts) == 1, name
        src, target, mode = mounts[0].split(":")
        assert mode == "ro"
        assert (path.parent / src).resolve() == MITRA.resolve()  # relative to the compose file
        assert src.startswith(".")
        assert "/scenario/mitra_cells.toml" in svc["command"]


def test_every_service_has_the_same_run_id(mitra):
    spec, _ = mitra
    ids = {name: flag(svc["command"], "--run-id") for name, svc in spec["services"].items() if name != "router"}
    assert set(ids.values()) == {"team-7"} and len(ids) == 19
    assert flag(spec["services"]["monitor"]["command"], "--out") == "/runs/team-7"


def test_default_run_id_is_the_scenario_name(run_rse, tmp_path):
    res = compose(run_rse, str(LKS), "-o", "-")
    assert res.returncode == 0, res.stderr
    spec = yaml.safe_load(res.stdout)
    assert {flag(s["command"], "--run-id") for n, s in spec["services"].items() if n != "router"} == {"lee_kim_shim"}
    assert set(spec["services"]) == {"router", "team", "plant", "monitor", *(f"agent-{i}" for i in agent_ids(LKS))}


def test_the_monitor_serves_the_web_viewer_on_published_ports_and_keeps_its_runs(mitra):
    spec, _ = mitra
    mon = spec["services"]["monitor"]
    cmd = mon["command"]
    assert "--serve-web" in cmd and flag(cmd, "--web-port") == "9090" and flag(cmd, "--grpc-port") == "9876"
    assert mon["ports"] == ["9090:9090", "9876:9876"]
    assert "runs:/runs" in mon["volumes"] and spec["volumes"] == {"runs": {}, "team": {}}
    for name, svc in spec["services"].items():
        if name not in ("monitor", "router"):
            assert "ports" not in svc, name


def test_agents_restart_on_failure_and_the_plant_does_not(mitra):
    spec, _ = mitra
    for name, svc in spec["services"].items():
        if name.startswith("agent-"):
            assert svc["restart"] == "on-failure", name
    assert "restart" not in spec["services"]["plant"] and "restart" not in spec["services"]["monitor"]


def test_overrides_and_seed_reach_every_process_and_dollars_survive_interpolation(run_rse, tmp_path):
    res = compose(run_rse, str(MITRA), "-o", str(tmp_path / "c.yml"), "--set", "run.rounds=200", "--seed", "7",
                  "--set", 'expect.0.label="below $LIMIT"', "--image", "registry.example/rse:1.0")
    assert res.returncode == 0, res.stderr
    text = (tmp_path / "c.yml").read_text()
    spec = yaml.safe_load(text)
    for name, svc in spec["services"].items():
        want = {"team": "registry.example/rse:1.0", "monitor": "registry.example/rse-monitor:1.0"}
        assert svc["image"] == want.get(name, "registry.example/rse-agent:1.0"), name
        if name != "team":  # the others read their slices, built with the overrides by the service team
            assert "--set" not in svc["command"] and "--seed" not in svc["command"], name
            continue
        cmd = svc["command"]
        sets = [cmd[i + 1] for i, a in enumerate(cmd) if a == "--set"]
        assert sets == ["run.rounds=200", 'expect.0.label="below $$LIMIT"'], name  # $$: a literal $ for compose
        assert flag(cmd, "--seed") == "7"
    first = text.splitlines()[1]
    assert "--seed 7" in first and "--image registry.example/rse:1.0" in first and "run.rounds=200" in first


def test_secure_each_service_mounts_only_its_own_credentials(secure):
    spec, path, certs = secure
    ids = agent_ids(MITRA)
    for name, svc in spec["services"].items():
        cert_mounts = [v for v in svc["volumes"] if v.split(":")[1].startswith("/certs/")]
        if name == "team":  # writes files, opens no session: no credentials at all
            assert cert_mounts == [] and "--secure" not in svc["command"]
            continue
        assert all(v.endswith(":ro") for v in svc["volumes"] if v != "runs:/runs"), name
        for v in cert_mounts:  # host file = container file name, from the certs directory
            src, target, _ = v.split(":")
            assert (path.parent / src).resolve() == (certs / Path(target).name).resolve()
        names = sorted(Path(v.split(":")[1]).name for v in cert_mounts)
        keys = [n for n in names if n.endswith(".key")]
        assert keys == [f"{name}.key"], (name, keys)  # its own key and no other
        expected = {"ca.pem", f"{name}.pem", f"{name}.key"}
        if name == "router":  # the agents' certificates (not keys): whom it admits
            expected |= {f"agent-{i}.pem" for i in ids}
        assert set(names) == expected, name
        cmd = svc["command"]
        assert flag(cmd, "--secure") == "/certs"
        if name == "router":
            assert flag(cmd, "--run-id") == "mitra_cells"  # the access control admits this run only
        else:
            assert flag(cmd, "--identity") == name


def test_secure_missing_credentials_is_exit_2_naming_the_file(run_rse, tmp_path):
    certs = fake_certs(tmp_path / "certs", range(1, 6))  # lee_kim_shim's agents 1..5
    (certs / "agent-3.key").unlink()
    res = compose(run_rse, str(LKS), "--secure", str(certs), "-o", str(tmp_path / "c.yml"))
    assert res.returncode == 2
    assert len(res.stderr.strip().splitlines()) == 1
    assert "agent-3.key" in res.stderr and "rse certs" in res.stderr
    assert not (tmp_path / "c.yml").exists()


@pytest.mark.parametrize(
    "args, message",
    [
        (["does/not/exist.toml"], "does/not/exist.toml: no such file"),
        ([str(LKS), "--set", "estimator.bogus=1"], "estimator.bogus: unknown key"),
        ([str(LKS), "--run-id", "a/b"], "--run-id: invalid run id 'a/b'"),
        ([str(LKS), "--image", "bad image"], "--image: invalid image name 'bad image'"),
        ([str(LKS), "--secure", "no/such/dir"], "--secure no/such/dir: no such directory"),
    ],
)
def test_bad_input_is_exit_2_with_one_line(run_rse, tmp_path, args, message):
    res = compose(run_rse, *args, "-o", str(tmp_path / "c.yml"))
    assert res.returncode == 2, res.stdout + res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], res.stderr
    assert not (tmp_path / "c.yml").exists()


def test_committed_docker_compose_yml_is_what_rse_compose_writes(run_rse, tmp_path):
    """The repository's docker-compose.yml cannot go stale: the same command, run in a copy
    of the layout (scenarios/mitra_cells.toml next to the file), writes the same bytes."""
    committed = ROOT / "docker-compose.yml"
    first = committed.read_text().splitlines()[1]
    m = re.search(r"Written by `(rse compose [^`]+)`", first)
    assert m and m.group(1) == "rse compose scenarios/mitra_cells.toml -o docker-compose.yml"
    (tmp_path / "scenarios").mkdir()
    shutil.copy(MITRA, tmp_path / "scenarios" / "mitra_cells.toml")
    res = compose(run_rse, "scenarios/mitra_cells.toml", "-o", "docker-compose.yml", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "docker-compose.yml").read_text() == committed.read_text(), \
        "docker-compose.yml is stale: run `rse compose scenarios/mitra_cells.toml -o docker-compose.yml`"


# ------------------------------------------------------------------ docker-compose config


def _compose_tool() -> list[str] | None:
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    if shutil.which("docker"):
        ok = subprocess.run(["docker", "compose", "version"], capture_output=True, timeout=30)
        if ok.returncode == 0:
            return ["docker", "compose"]
    return None


@pytest.mark.parametrize("which", ["committed", "secure"])
def test_docker_compose_config_accepts_the_file(which, secure):
    tool = _compose_tool()
    if tool is None:
        pytest.skip("neither docker-compose nor the docker compose plugin is installed (apt-get install docker-compose)")
    path = ROOT / "docker-compose.yml" if which == "committed" else secure[1]
    res = subprocess.run([*tool, "-f", str(path), "config", "-q"], capture_output=True, text=True, timeout=60,
                         cwd=path.parent)
    assert res.returncode == 0, res.stderr
    assert "WARN" not in res.stderr.upper(), res.stderr
    full = subprocess.run([*tool, "-f", str(path), "config"], capture_output=True, text=True, timeout=60,
                          cwd=path.parent)
    resolved = yaml.safe_load(full.stdout)
    assert set(resolved["services"]) == set(load(path)["services"])
    team_mounts = resolved["services"]["team"]["volumes"]  # the one service that reads the scenario
    src = team_mounts[0]["source"] if isinstance(team_mounts[0], dict) else team_mounts[0].split(":")[0]
    assert Path(src).resolve() == MITRA.resolve()  # the relative path resolves to the scenario


# ------------------------------------------------------------------ Dockerfile


def _instructions(text: str) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) of a Dockerfile, continuation lines joined, comments dropped."""
    joined = re.sub(r"\\\n", " ", "\n".join(l for l in text.splitlines() if not l.lstrip().startswith("#")))
    out = []
    for line in joined.splitlines():
        if line.strip():
            word, _, rest = line.strip().partition(" ")
            out.append((word.upper(), rest.strip()))
    return out


def _stages(ins: list[tuple[str, str]]) -> dict[str, dict]:
    """Build stages of a Dockerfile: name -> {"from": image or stage, "ins": its instructions}."""
    stages: dict[str, dict] = {}
    for k, a in ins:
        if k == "FROM":
            image, _, name = a.partition(" AS ")
            current = stages.setdefault(name.strip() or image, {"from": image.strip(), "ins": []})
        else:
            current["ins"].append((k, a))
    return stages


def _chain(stages: dict[str, dict], name: str) -> list[tuple[str, str]]:
    """The instructions of ``name`` with those of the stages it is built on, base first."""
    parent = stages[name]["from"]
    return (_chain(stages, parent) if parent in stages else []) + stages[name]["ins"]


def test_dockerfile_role_targets_slim_base_non_root_user_and_healthcheck():
    ins = _instructions((ROOT / "Dockerfile").read_text())
    assert ins[0] == ("FROM", "python:3.11-slim AS base")
    stages = _stages(ins)
    assert {"agent", "monitor", "full"} <= set(stages)
    assert list(stages)[-1] == "full"  # `docker build .` without --target: every rse command
    for name in ("agent", "monitor", "full"):
        chain = _chain(stages, name)
        kinds = [k for k, _ in chain]
        users = [a for k, a in chain if k == "USER"]
        assert users[-1] == "rse", name
        last_user = len(kinds) - 1 - kinds[::-1].index("USER")
        assert last_user > max(i for i, k in enumerate(kinds) if k == "RUN"), name  # nothing runs as root after
        health = dict(chain)["HEALTHCHECK"]
        assert json.loads(health.split("CMD", 1)[1]) == ["python", "-m", "agents.healthcheck"], name
        assert "7447" in " ".join(a for k, a in chain if k == "EXPOSE"), name
    assert (ROOT / "agents" / "healthcheck.py").is_file()
    full = dict(_chain(stages, "full"))
    assert json.loads(full["ENTRYPOINT"]) == ["rse"]
    exposed = " ".join(a for k, a in _chain(stages, "monitor") if k == "EXPOSE").split()
    assert {"9090", "9876"} <= set(exposed)
    assert "useradd" in " ".join(a for k, a in stages["base"]["ins"] if k == "RUN")


def test_dockerfile_role_images_install_requirements_of_pyproject():
    """The agent and monitor stages name their packages with pyproject.toml's own specifiers,
    and the agent stage only what an agent process needs."""
    stages = _stages(_instructions((ROOT / "Dockerfile").read_text()))
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    known = set(meta["dependencies"]) | {r for e in meta["optional-dependencies"].values() for r in e}

    def installed(stage: str) -> list[str]:
        out = []
        for k, a in stages[stage]["ins"]:
            if k == "RUN" and "pip install" in a:
                out += re.findall(r'"([A-Za-z0-9_.-]+[<>=!~][^"]*)"', a.split("&&")[0])
        return out

    agent, monitor = installed("agent-deps"), installed("monitor-deps")
    assert {re.split(r"[<>=!~]", r)[0] for r in agent} == {"numpy", "eclipse-zenoh", "uvloop", "msgpack", "click", "rich", "psutil"}
    # pydantic: the built experiment the monitor reads holds the validated scenario
    assert {re.split(r"[<>=!~]", r)[0] for r in monitor} == {"rerun-sdk", "pyarrow", "pydantic"}
    for r in agent + monitor:
        assert r in known, f"Dockerfile requirement {r} is not one of pyproject.toml's"


def test_dockerfile_copies_what_the_package_is_built_from_and_the_context_excludes_secrets():
    ins = _instructions((ROOT / "Dockerfile").read_text())
    copied = set()
    for k, a in ins:
        if k == "COPY" and not a.startswith("--from="):
            *srcs, _ = a.split()
            copied |= set(srcs)
    for src in copied:
        assert (ROOT / src).exists(), src
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())
    packages = {p.rstrip("*") for p in meta["tool"]["setuptools"]["packages"]["find"]["include"]}
    assert packages | {"pyproject.toml", meta["project"]["readme"]} <= copied
    ignore = [l.strip() for l in (ROOT / ".dockerignore").read_text().splitlines() if l.strip() and not l.startswith("#")]
    assert {".git", "certs", "**/*.key", "runs"} <= set(ignore)
    assert not copied & set(ignore)


# ------------------------------------------------------------------ health check


def test_expected_sockets_of_rse_command_lines():
    from agents.healthcheck import expected_sockets, rse_argv

    e = expected_sockets(["agent", "--id", "3", "/s.toml", "--client", "--connect", "tcp/router:7447"])
    assert (e.command, e.listen, e.connect) == ("agent", [], [7447])
    e = expected_sockets(["router", "--listen=tcp/0.0.0.0:7000", "--listen", "tls/[::]:7001"])
    assert (e.command, e.listen, e.connect) == ("router", [7000, 7001], [])
    assert expected_sockets(["router"]).listen == [7447]  # its default
    assert expected_sockets(["check", "x.toml"]).listen == [] and expected_sockets([]).command == ""
    assert rse_argv(["/usr/local/bin/python3.11", "/usr/local/bin/rse", "plant", "x"]) == ["plant", "x"]
    assert rse_argv(["rse", "router"]) == ["router"]
    assert rse_argv(["python", "-m", "agents.cli", "monitor"]) == ["monitor"]
    assert rse_argv(["python", "-m", "agents.healthcheck"]) is None
    assert rse_argv(["/sbin/docker-init", "--", "rse", "router"]) is None  # init: true's PID 1 is not rse
    assert rse_argv(["/usr/bin/tini", "rse", "plant"]) is None


def test_find_rse_skips_the_init_and_itself():
    from agents.healthcheck import find_rse

    class P:
        def __init__(self, pid, cmdline):
            self.pid, self._cmd = pid, cmdline

        def cmdline(self):
            return self._cmd

    tree = [P(1, ["/sbin/docker-init", "--", "rse", "router", "--listen", "tcp/0.0.0.0:7447"]),
            P(7, ["/usr/local/bin/python3.11", "/usr/local/bin/rse", "router", "--listen", "tcp/0.0.0.0:7447"]),
            P(9, ["/usr/local/bin/python3.11", "-m", "agents.healthcheck"])]
    proc, argv = find_rse(tree, me=9)
    assert proc.pid == 7 and argv == ["router", "--listen", "tcp/0.0.0.0:7447"]
    assert find_rse(tree[:1] + tree[2:], me=9) is None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _health(pid: int) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "agents.healthcheck", "--pid", str(pid)], capture_output=True,
                          text=True, timeout=60, cwd=ROOT)


def test_healthcheck_against_real_sockets(procs):
    """A listener on its --listen port and a client connected to its --connect port are
    healthy; a client whose port has no connection, or a gone process, is not (exit 1)."""
    port, closed = _free_port(), _free_port()
    server = procs.start([sys.executable, "-c", (
        "import socket, time\n"
        f"s = socket.create_server(('127.0.0.1', {port})); conns = []\n"
        "while True: conns.append(s.accept())"), "--listen", f"tcp/127.0.0.1:{port}"])
    deadline = time.monotonic() + 20
    while _health(server.pid).returncode != 0 and time.monotonic() < deadline:
        time.sleep(0.2)
    res = _health(server.pid)
    assert res.returncode == 0 and res.stdout.strip() == f"healthy: process {server.pid}: listening on {port}"
    client = procs.start([sys.executable, "-c", (
        "import socket, time\n"
        f"c = socket.create_connection(('127.0.0.1', {port})); time.sleep(60)"), "--connect", f"tcp/127.0.0.1:{port}"])
    deadline = time.monotonic() + 20
    while _health(client.pid).returncode != 0 and time.monotonic() < deadline:
        time.sleep(0.2)
    res = _health(client.pid)
    assert res.returncode == 0 and f"connected to port {port}" in res.stdout
    lost = procs.start([sys.executable, "-c", "import time; time.sleep(60)", "--connect", f"tcp/127.0.0.1:{closed}"])
    res = _health(lost.pid)
    assert res.returncode == 1
    assert res.stdout.strip() == f"unhealthy: process {lost.pid}: no connection to port {closed} (its Zenoh session is not connected)"
    lost.kill()
    lost.wait()
    res = _health(lost.pid)
    assert res.returncode == 1 and res.stdout.startswith("unhealthy:")


def test_healthcheck_of_rse_router(procs):
    p, ep = procs.router("--listen", "tcp/127.0.0.1:0")
    port = int(ep.rsplit(":", 1)[1])
    res = _health(p.pid)
    assert res.returncode == 0, res.stdout
    assert res.stdout.strip() == f"healthy: rse router: listening on {port}"


# ------------------------------------------------------------------ a compose run without Docker


SMALL = ("run.dt=0.01", "run.duration=6", "output.window=[4.0, 6.0]", "expect=[]")


def _materialize(name: str, svc: dict, compose_dir: Path, root: Path) -> Path:
    """A directory standing for the container of ``name``: only its mounts, at their paths
    (a named volume: one directory under ``root/_volumes``, linked into each service)."""
    d = root / name
    d.mkdir()
    for v in svc.get("volumes", []):
        src, target, *_ = v.split(":")
        dst = d / target.lstrip("/")
        if not src.startswith((".", "/")):  # a named volume (runs, team)
            vol = root / "_volumes" / src
            vol.mkdir(parents=True, exist_ok=True)
            dst.parent.mkdir(parents=True, exist_ok=True)
            dst.symlink_to(vol, target_is_directory=True)
            continue
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2((compose_dir / src).resolve(), dst)
    return d


def _localize(cmd: list[str], d: Path, port: int, ports: dict[str, int]) -> list[str]:
    """Container paths -> the service's directory; the router's host name and ports -> loopback."""
    out = []
    for a in cmd:
        if a.startswith(("/scenario", "/certs", "/runs", "/team")):
            a = str(d / a.lstrip("/"))
        elif a == "tcp/router:7447":
            a = f"tcp/127.0.0.1:{port}"
        elif a == "tcp/0.0.0.0:7447":
            a = f"tcp/127.0.0.1:{port}"
        elif a in ports:
            a = str(ports[a])
        out.append(a)
    return out


@pytest.mark.multiprocess
def test_a_secure_compose_file_runs_with_each_service_seeing_only_its_mounts(run_rse, procs, tmp_path):
    """rse compose --secure of lee_kim_shim.toml (shortened), each service's command run as
    a local process in a directory holding only that service's mounts (its own key, ca.pem,
    the scenario): the team runs to the end over the TLS router, every client is healthy
    while it waits for its team, the monitor writes the run directory and serves the web viewer."""
    pytest.importorskip("cryptography", reason="rse certs needs the cryptography package (pip install '.[secure]')")
    from transport.certs import write_certs

    ids = agent_ids(LKS)
    certs = tmp_path / "certs"
    write_certs(certs, ["router", "plant", "monitor", *(f"agent-{i}" for i in ids)])
    args = [a for s in SMALL for a in ("--set", s)]
    res = compose(run_rse, str(LKS), "-o", str(tmp_path / "deploy" / "compose.yml"), "--secure", str(certs),
                  "--run-id", "compose-test", *args)
    assert res.returncode == 0, res.stderr
    spec = load(tmp_path / "deploy" / "compose.yml")
    port = _free_port()
    ports = {"9090": _free_port(), "9876": _free_port()}
    root = tmp_path / "containers"
    root.mkdir()
    dirs = {name: _materialize(name, svc, tmp_path / "deploy", root) for name, svc in spec["services"].items()}
    assert sorted(p.name for p in (dirs["agent-2"] / "certs").iterdir()) == ["agent-2.key", "agent-2.pem", "ca.pem"]
    run = {}
    router, ep = procs.router(*_localize(spec["services"]["router"]["command"], dirs["router"], port, ports)[1:])
    assert ep == f"tls/127.0.0.1:{port}"
    team = procs.start(rse_cmd(*_localize(spec["services"]["team"]["command"], dirs["team"], port, ports)))
    assert team.wait(timeout=120) == 0, team.communicate()[1]  # the design once: the agents start after it
    # every service but the last agent: the team cannot start without it, so plant, monitor
    # and the other agents stay connected to the router, waiting, while their health is checked
    # (not a race with a 600-round run that a quiet machine finishes in seconds)
    last = f"agent-{ids[-1]}"
    for name, svc in spec["services"].items():
        if name not in ("router", "team", last):
            run[name] = procs.start(rse_cmd(*_localize(svc["command"], dirs[name], port, ports)))
    health = {}
    deadline = time.monotonic() + 120  # only a hang reaches it
    while time.monotonic() < deadline and len(health) < 3:
        for name in ("plant", "agent-1", "monitor"):
            assert run[name].poll() is None, f"{name} exited while waiting for its team: {run[name].communicate()[1]}"
            if name not in health and _health(run[name].pid).returncode == 0:
                health[name] = True
        time.sleep(0.3)
    assert set(health) == {"plant", "agent-1", "monitor"}, health  # connected to the router
    run[last] = procs.start(rse_cmd(*_localize(spec["services"][last]["command"], dirs[last], port, ports)))
    assert run["plant"].wait(timeout=300) == 0, run["plant"].communicate()[1]
    for i in ids:
        p = run[f"agent-{i}"]
        assert p.wait(timeout=60) == 0, p.communicate()[1]
    out = dirs["monitor"] / "runs" / "compose-test"
    deadline = time.monotonic() + 120
    while not (out / "summary.json").exists() and time.monotonic() < deadline:
        time.sleep(0.2)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["rounds"] == 600
    assert (out / "recording.rrd").stat().st_size > 0 and (out / "metrics.parquet").exists()
    mon = run["monitor"]
    assert mon.poll() is None  # still serving the recording after the run
    with urllib.request.urlopen(f"http://127.0.0.1:{ports['9090']}/", timeout=10) as r:
        assert r.status == 200
    os.killpg(mon.pid, signal.SIGTERM)
    mon.wait(timeout=10)
    assert router.poll() is None  # the router stays up (restart: unless-stopped)
    router.send_signal(signal.SIGINT)
    assert router.wait(timeout=10) == 0
