"""Containers for real: the images built, ``docker compose up`` of files written by
``rse compose``, run to completion, the run directory read from the volume.

Needs a Docker daemon and a compose tool (``apt-get install docker.io docker-compose``);
skipped with the reason otherwise. When nothing answers and the tests run as root with
``dockerd`` installed, :func:`tests.deploy.docker.unavailable` starts ``dockerd`` itself.
The images are built once per session (layer cache: a rebuild after a code change takes
seconds); where ``python:3.11-slim`` cannot be pulled a stand-in is built from Debian
(see tests/deploy/docker.py). The first build takes minutes.

Cases (each a compose project of its own, taken down in ``finally``):

* **plain**: ``mitra_cells.toml`` (router, team, plant, monitor, 16 agents; the file the
  repository's ``docker-compose.yml`` is): every container healthy by its health check
  (the seconds from ``up`` printed: the issue's 30 s is a figure of the machine, reported,
  not a timed assertion), each role on its image, the plant exits 0, the monitor's run directory in the volume
  ``runs`` holds metrics, summary and recording, both ``[[expect]]`` bounds hold and the
  errors equal ``rse simulate``'s; the web viewer answers on the monitor's port;
  ``docker compose down`` leaves no container;
* **secure**: ``lee_kim_shim.toml`` with ``rse compose --secure`` (certificates of
  ``rse certs``): mutual TLS and the router's access control between containers; the same
  checks; Ctrl-C on a foreground ``up`` leaves no container running;
* **container failure**: agent 3's ``rse`` process killed inside its container while the
  team runs: Docker restarts the container (``restart: on-failure``), the agent rejoins
  (``join``, ``leave``, ``join`` in the summary), the run completes within the scenario's
  bounds, agent 3 included.

Host ports: the generated files publish 7447, 9090 and 9876 on the host; here they are
published on ephemeral host ports instead, so a test never collides with a service of
the machine. The only other changes to a generated file are flags of the plant: a 300 s
start-up timeout (20 containers starting at once on a loaded host take longer than the
default 60 s to join), a 30 s lockstep deadline where the run is compared with ``rse
simulate`` (a round that waits out the default 1 s deadline on a loaded host goes on
without a late agent, and the run no longer equals the simulator's), a rate cap in the
failure case.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
import urllib.request
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import yaml

from tests.conftest import SCENARIOS, rse
from tests.deploy import docker as dk

pytestmark = [pytest.mark.slow, pytest.mark.multiprocess]

MITRA = SCENARIOS / "mitra_cells.toml"
LKS = SCENARIOS / "lee_kim_shim.toml"
HEALTHY_WITHIN = 30.0  # seconds from `up` until every container is healthy (the figure: reported)
#: hang bounds, generous for a loaded host (not measurements)
STARTUP = ["--startup-timeout", "300"]


@pytest.fixture(scope="module")
def images() -> dict[str, int]:
    """The role images, built (or found in the layer cache); their sizes in bytes."""
    why = dk.unavailable()
    if why:
        pytest.skip(f"Docker: {why}")
    how = dk.base_image()
    times = dk.build_images()
    sizes = {target: dk.image_size(tag) for target, tag in dk.TARGETS.items()}
    base = dk.image_size(dk.BASE)
    print(f"\nbase {dk.BASE} ({how}): {base / 1e6:.0f} MB; " + "; ".join(
        f"{t}: {s / 1e6:.0f} MB (+{(s - base) / 1e6:.0f} MB, built in {times[t]:.0f} s)" for t, s in sizes.items()))
    return {"base": base, **sizes}


def write_compose(tmp: Path, scenario: Path, *args: str, plant: tuple[str, ...] = ()) -> tuple[Path, dict]:
    """``rse compose SCENARIO ARGS -o tmp/compose.yml``, host ports made ephemeral, the
    plant's start-up timeout raised and ``plant`` added to its flags."""
    path = tmp / "compose.yml"
    res = rse("compose", str(scenario), "-o", str(path), *args)
    assert res.returncode == 0, res.stderr
    spec = yaml.safe_load(path.read_text())
    for svc in spec["services"].values():
        if "ports" in svc:
            svc["ports"] = [p.split(":")[-1] for p in svc["ports"]]
    spec["services"]["plant"]["command"] += [*STARTUP, *plant]
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    return path, spec


def check_role_images(run: dk.ComposeRun, spec: dict) -> None:
    """Each container runs its role's image: the monitor the monitor image, the design
    (team) the full one, everything else the agent image."""
    want = {"monitor": dk.TARGETS["monitor"], "team": dk.TARGETS["full"]}
    for name in spec["services"]:
        assert run.inspect(name)["Config"]["Image"] == want.get(name, dk.TARGETS["agent"]), name


def _ts(stamp: str) -> float:
    """Docker's RFC 3339 time stamp (nanoseconds) as a POSIX time."""
    from datetime import datetime

    head, _, frac = stamp.rstrip("Z").partition(".")
    return datetime.fromisoformat(head + "+00:00").timestamp() + float("0." + (frac[:6] or "0"))


def wait_healthy(run: dk.ComposeRun, services: list[str], t_up: float, timeout: float = 120) -> dict[str, float]:
    """Wait until every service's container has passed a health check (or exited 0 before
    its first one); fails on a non-zero exit. Returns, per service,
    the seconds from ``t_up`` (a POSIX time taken before ``up``) to its ``health_status:
    healthy`` event (Docker's own time stamp; NaN: exited before its first check).
    ``run.watch_health()`` must have been called before ``up``."""
    ids = {run.container(s): s for s in services}
    seen: dict[str, float] = {}
    end = time.monotonic() + timeout
    while len(seen) < len(services) and time.monotonic() < end:
        for cid, (t, _) in list(run.health.items()):
            if cid in ids:
                seen.setdefault(ids[cid], t - t_up)
        todo = [c for c, s in ids.items() if s not in seen]
        if todo:
            for st in json.loads(dk.docker("inspect", *todo).stdout):
                s = ids[st["Id"]]
                if st["State"]["Status"] == "exited" and s not in seen and st["Id"] not in run.health:
                    assert st["State"]["ExitCode"] == 0, f"{s} exited {st['State']['ExitCode']}\n{run.logs(s)}"
                    seen[s] = float("nan")  # done before its first check
        time.sleep(1.0)
    assert len(seen) == len(services), f"not healthy within {timeout} s: {set(services) - set(seen)}\n{run.logs()}"
    return seen


def report_health(run: dk.ComposeRun, healthy: dict[str, float], t_cmd: float) -> dict[str, float]:
    """Print the start-up figures; return the containers not healthy within 30 s of ``up``
    (printed at the end of a test: a wall-clock figure of the machine, not asserted)."""
    checked = {s: t for s, t in healthy.items() if not np.isnan(t)}
    last = max(checked, key=checked.get)
    print(f"\nup -d returned after {t_cmd:.1f} s; router healthy at {healthy['router']:.1f} s, every container at "
          f"{checked[last]:.1f} s (last: {last}); median {np.median(list(checked.values())):.1f} s")
    if run.unhealthy:  # a check that timed out 3 times in a row (a loaded host): reported, the run decides
        print(f"health checks that failed in a row, marking a container unhealthy for a while: {len(run.unhealthy)}")
    return {s: round(t, 1) for s, t in checked.items() if t > HEALTHY_WITHIN}


def read_run(run: dk.ComposeRun, run_id: str, dest: Path, timeout: float = 120) -> Path:
    """Wait for the monitor's summary.json in the volume, then copy the run directory out."""
    target = f"/runs/{run_id}"
    run.wait(lambda: dk.docker("exec", run.container("monitor"), "test", "-f", f"{target}/summary.json",
                               check=False).returncode == 0, timeout, "the monitor's summary.json")
    # summary.json is written last, by rename: once it is there the run directory is complete
    return run.copy_out("monitor", target, dest)


def check_expectations(out: Path) -> dict:
    summary = json.loads((out / "summary.json").read_text())
    assert summary["expectations"], "the scenario has [[expect]] bounds"
    for e in summary["expectations"]:
        assert e["ok"], e
    for name in ("metrics.parquet", "summary.json", "recording.rrd"):
        assert (out / name).stat().st_size > 0, name
    return summary


def no_container_left(run: dk.ComposeRun, running_only: bool = False) -> list[str]:
    args = ["ps", "-q", "--filter", f"label=com.docker.compose.project={run.project}"]
    return dk.docker(*(args if running_only else [args[0], "-a", *args[1:]])).stdout.split()


def errors(out: Path) -> dict[tuple[int, int, str], float]:
    m = pq.read_table(out / "metrics.parquet", columns=["k", "agent", "block", "error_2"]).to_pydict()
    return {(k, a, b): e for k, a, b, e in zip(m["k"], m["agent"], m["block"], m["error_2"])}


# ------------------------------------------------------------------ images


def test_image_sizes(images):
    """The agent image adds at most 150 MB to its base; the others are reported beside it."""
    added = images["agent"] - images["base"]
    assert added <= 150e6, f"the agent image adds {added / 1e6:.0f} MB to {dk.BASE}"
    assert images["monitor"] > images["agent"]
    out = dk.docker("run", "--rm", "--entrypoint", "python", dk.TARGETS["agent"], "-c",
                    "import numpy, zenoh, msgpack, agents, estimation, transport\n"
                    "import importlib.util as u\n"
                    "print(sorted(m for m in ('scipy', 'cvxpy', 'rerun', 'pyarrow', 'pydantic', 'networkx') "
                    "if u.find_spec(m)))").stdout
    assert out.strip() == "[]", f"the agent image carries {out.strip()}"


# ------------------------------------------------------------------ runs


def test_compose_up_mitra_cells(images, tmp_path):
    # lockstep never gives up on a late agent of a loaded host
    path, spec = write_compose(tmp_path, MITRA, "--run-id", "mitra-docker", plant=("--deadline", "30"))
    services = list(spec["services"])
    with dk.ComposeRun(path) as run:
        run.watch_health()
        t_up = time.time()
        t_cmd = run.up()
        healthy = wait_healthy(run, services, t_up)
        late = report_health(run, healthy, t_cmd)
        check_role_images(run, spec)
        assert run.wait_exit("plant", 600) == 0, run.logs("plant")
        t_done = time.time() - t_up
        out = read_run(run, "mitra-docker", tmp_path / "run")
        port = dk.docker("port", run.container("monitor"), "9090").stdout.split()[0].rsplit(":", 1)[1]
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10) as page:
            assert page.status == 200 and b"<html" in page.read().lower()
        for i in range(1, 17):
            assert run.wait_exit(f"agent-{i}", 30) == 0
        t0 = time.monotonic()
        run.down()
        t_down = time.monotonic() - t0
        assert no_container_left(run) == []
    print(f"plant done {t_done:.1f} s after up; down in {t_down:.1f} s")
    summary = check_expectations(out)
    final = summary["expectations"][0]["value"]
    assert final <= 1e-9
    sim = tmp_path / "sim"
    res = rse("simulate", str(MITRA), "--out", str(sim), "--no-progress")
    assert res.returncode == 0, res.stderr
    a, b = errors(out), errors(sim)
    assert a.keys() == b.keys()
    worst = max(abs(a[k] - b[k]) / max(1.0, abs(b[k])) for k in a)
    assert worst <= 1e-9, f"containers differ from rse simulate by {worst:.3g}"  # lockstep: the simulator's run
    print(f"not healthy within {HEALTHY_WITHIN:g} s of up: {late or 'none'}")


class RoundWatch:
    """The newest round of a plain (not ``--secure``) compose run, seen from this host: a
    Zenoh client of the router's published port subscribed to the true state the plant
    publishes each round (its message's round stamp ``k``)."""

    def __init__(self, port: str, run_id: str) -> None:
        import msgpack
        import zenoh

        from transport.keys import Keys
        from transport.zenoh_session import make_config

        self.round = -1
        self.session = zenoh.open(make_config(mode="client", connect=[f"tcp/127.0.0.1:{port}"]))

        def seen(sample) -> None:
            self.round = max(self.round, int(msgpack.unpackb(bytes(sample.payload.to_bytes()))["k"]))

        self.sub = self.session.declare_subscriber(Keys(run_id).plant_truth(), seen)

    def wait(self, k: int, timeout: float) -> None:
        end = time.monotonic() + timeout
        while self.round < k:
            assert time.monotonic() < end, f"round {k} not reached within {timeout} s (at {self.round})"
            time.sleep(0.05)

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


def test_compose_up_secure_lee_kim_shim_and_ctrl_c(images, tmp_path):
    """rse compose --secure: every link mutual TLS, the router's access control between the
    containers; the run completes within the scenario's bounds; Ctrl-C on a foreground
    `up` stops every container."""
    pytest.importorskip("cryptography", reason="rse certs needs the cryptography package (pip install '.[secure]')")
    certs = tmp_path / "certs"
    res = rse("certs", str(certs), "--scenario", str(LKS))
    assert res.returncode == 0, res.stderr
    if os.geteuid() == 0:  # the containers run as uid 1000; the keys are 0600 (docs/deployment.md)
        for key in certs.glob("*.key"):
            os.chown(key, 1000, 1000)
    path, spec = write_compose(tmp_path, LKS, "--secure", str(certs), "--run-id", "lks-secure")
    assert spec["services"]["router"]["command"][-4:] == ["--secure", "/certs", "--run-id", "lks-secure"]
    with dk.ComposeRun(path) as run:
        log = open(tmp_path / "up.log", "w")
        run.watch_health()
        t_up = time.time()
        up = subprocess.Popen([*run.cmd, "up", "--no-build"], cwd=path.parent, stdout=log, stderr=subprocess.STDOUT,
                              start_new_session=True)
        try:
            run.wait(lambda: len(run.containers()) == len(spec["services"]), 120, "every container created")
            healthy = wait_healthy(run, list(spec["services"]), t_up)
            late = report_health(run, healthy, float("nan"))
            check_role_images(run, spec)
            assert run.wait_exit("plant", 600) == 0, run.logs("plant")
            out = read_run(run, "lks-secure", tmp_path / "run")
            router_log = run.logs("router", tail=200)
            assert "tls/" in router_log, router_log
            t0 = time.monotonic()
            os.killpg(up.pid, signal.SIGINT)  # Ctrl-C in the terminal of `up`
            up.wait(timeout=60)
            t_stop = time.monotonic() - t0
            assert no_container_left(run, running_only=True) == []
            print(f"Ctrl-C on up: every container stopped after {t_stop:.1f} s")
        finally:
            if up.poll() is None:
                os.killpg(up.pid, signal.SIGKILL)
            log.close()
    summary = check_expectations(out)
    print("expectations:", [(e["label"][:40], round(e["value"], 4)) for e in summary["expectations"]])
    assert {m["role"] for m in summary["membership"]} >= {"agent", "plant"}
    print(f"not healthy within {HEALTHY_WITHIN:g} s of up: {late or 'none'}")


def test_an_agent_killed_in_its_container_restarts_and_rejoins(images, tmp_path):
    """Agent 3's process killed (SIGKILL) inside its container at t >= 12 s of a lockstep run
    capped at 100 rounds/s: Docker restarts the container, the agent rejoins the running
    team, and everyone, agent 3 included, is within the scenario's bounds at the end."""
    duration = 41.0
    path, spec = write_compose(tmp_path, LKS, "--run-id", "lks-restart", "--set", f"run.duration={duration}",
                               "--set", f"output.window=[{duration - 1}, {duration}]",
                               plant=("--rate", "100"))  # lockstep, at most 100 rounds/s
    with dk.ComposeRun(path) as run:
        run.up()
        port = dk.docker("port", run.container("router"), "7447").stdout.split()[0].rsplit(":", 1)[1]
        watch = RoundWatch(port, "lks-restart")
        try:
            watch.wait(1200, 400)
            cid = run.container("agent-3")
            kill = ("import os, signal, psutil\nfrom agents.healthcheck import find_rse\n"
                    "p, _ = find_rse(psutil.process_iter(), os.getpid())\nos.kill(p.pid, signal.SIGKILL)\nprint(p.pid)")
            k_before = watch.round
            # its exit status may be the container's end (the exec dies with it): the restart count decides
            dk.docker("exec", cid, "python", "-c", kill, check=False)
            k_kill = watch.round
            run.wait(lambda: run.inspect("agent-3")["RestartCount"] >= 1, 60, "agent-3 restarted")
            k_restart = watch.round
            assert run.wait_exit("plant", 300) == 0, run.logs("plant")
            out = read_run(run, "lks-restart", tmp_path / "run")
            assert run.wait_exit("agent-3", 60) == 0, run.logs("agent-3")
            restarts = run.inspect("agent-3")["RestartCount"]
        finally:
            watch.close()
    print(f"\nagent 3 killed at round {k_kill}, its container restarted by round {k_restart} "
          f"(restart count {restarts}); run done")
    assert restarts == 1
    summary = check_expectations(out)
    events = [ev for ev in summary["membership"] if ev["role"] == "agent" and ev["id"] == 3]
    assert [ev["event"] for ev in events[:3]] == ["join", "leave", "join"], summary["membership"]
    k_left, k_back = events[1]["round"], events[2]["round"]  # as the monitor saw them
    m = pq.read_table(out / "metrics.parquet", columns=["k", "agent", "block", "error_inf"]).to_pydict()
    k, agent, e = np.array(m["k"]), np.array(m["agent"]), np.array(m["error_inf"])
    a3 = (np.array(m["block"]) == "x") & (agent == 3)
    t = k * 0.01
    assert k_before <= k_left <= k_kill + 100, (k_before, k_left, k_kill)  # the leave is the kill
    assert np.isnan(e[a3 & (k > k_left) & (k < k_back)]).all()  # dead: no estimate while it was gone
    rejoined = k[a3 & ~np.isnan(e) & (k > k_back)]
    assert rejoined.size, "agent 3 reported nothing after its restart"
    worst = np.nanmax(e[a3 & (t >= duration - 1)])
    assert worst <= 0.25  # re-converged (the scenario's bound over the window)
    print(f"monitor: agent 3 left at round {k_left}, back at round {k_back} ({(k_back - k_left) * 0.01:.1f} s of "
          f"scenario at <= 100 rounds/s), reports from round {rejoined.min()}; its error over the last second {worst:.4f}")
