"""A docker-compose file for a scenario: one container per process of the team.

``rse compose SCENARIO`` (:mod:`agents.cli.compose`) writes it with :func:`compose_spec`
and :func:`render`. The images are the Dockerfile's role targets (:func:`role_images`):
the *full* image (every ``rse`` command, the offline design stack), the slim *agent*
image (numpy, Zenoh, msgpack, click and the package) and the *monitor* image (the agent
image with Rerun, pyarrow and pydantic), all with ``rse`` as entry point. The services:

* ``router`` (agent image): ``rse router --listen tcp/0.0.0.0:7447`` (port 7447
  published, so agents on other hosts can join); healthy once it listens (``python -m
  agents.healthcheck``), and every other service waits for that;
* ``team`` (full image, one-shot): builds the experiment once, the offline design
  included, and writes ``team.json``, each agent's slice, the plant's slice and the built
  experiment the monitor reads (:func:`write_team`) to the volume ``team``; it exits 0 and
  every other process of the team waits for that;
* ``plant`` (agent image), ``monitor`` (monitor image) and ``agent-{i}`` (agent image,
  one per agent of the scenario): Zenoh clients of the router (``--client --connect
  tcp/router:7447``) with the same run id, each started from its part of the team
  directory (``--team /team/team.json``: no scenario file, no design); only ``team``
  mounts the scenario file, read-only at ``/scenario/NAME.toml``;
* the monitor writes the run directory to the volume ``runs`` (``/runs/RUN_ID``) and
  serves the Rerun web viewer (ports 9090 and 9876 published);
* agents restart on failure (a crashed agent rejoins the running team from its slice);
* every long-running service's health check runs every few seconds (the images' 10 s
  interval would delay ``healthy`` by up to 10 s after a process joins).

With ``secure`` (a directory written by ``rse certs``) every process presents its own TLS
identity: a service mounts ``ca.pem`` and its own ``IDENTITY.pem`` / ``IDENTITY.key``
read-only under ``/certs`` and nothing else (the router also mounts the agents'
certificates, not their keys: they name the agents it admits). With ``peers`` too there is
no router: every process is a secure peer listening on ``tls/0.0.0.0:7450`` and linked to
the others by service name, and it also mounts the team's certificates (public: its ingress
rules and pairwise keys need them).
"""

from __future__ import annotations

import os
import shlex
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from estimation.errors import ScenarioError

if TYPE_CHECKING:
    from scenarios.build import Experiment

__all__ = ["DEFAULT_IMAGE", "ROUTER_PORT", "WEB_PORT", "GRPC_PORT", "default_run_id", "compose_spec", "render",
           "role_images", "secure_mounts", "write_team"]

DEFAULT_IMAGE = "resilient-state-estimation:latest"
ROUTER_PORT = 7447
PEER_PORT = 7450  # every secure peer's endpoint in a compose file of peers (rse compose --secure DIR --peers)
WEB_PORT = 9090  # the Rerun web viewer page (rse monitor --web-port)
GRPC_PORT = 9876  # the gRPC endpoint the page reads the recording from (--grpc-port)
ROUTER_HOST = "router"  # the router's service name: its host name on the compose network
SCENARIO_DIR = "/scenario"
CERTS_DIR = "/certs"
RUNS_DIR = "/runs"
TEAM_DIR = "/team"  # the volume "team" in an agent (read-only); the team service writes it at /runs
HEALTHCHECK = ["CMD", "python", "-m", "agents.healthcheck"]
#: the check of a client of the router (one ``python -m agents.healthcheck``: ~0.05 s of CPU)
CLIENT_HEALTH = {"interval": "3s", "timeout": "10s", "retries": 5, "start_period": "60s"}


class Quoted(str):
    """A string the YAML file writes in double quotes (``"9090:9090"``)."""


class Flow(list):
    """A list the YAML file writes on one line (commands)."""


def role_images(image: str) -> dict[str, str]:
    """The images of the roles for ``image`` (the full one, ``NAME[:TAG]``): ``full`` is
    ``image`` itself, ``agent`` is ``NAME-agent[:TAG]``, ``monitor`` ``NAME-monitor[:TAG]``
    (the Dockerfile's targets, tagged as its header says)."""
    slash = image.rfind("/")
    colon = image.rfind(":")
    name, tag = (image[:colon], image[colon:]) if colon > slash else (image, "")
    return {"full": image, "agent": f"{name}-agent{tag}", "monitor": f"{name}-monitor{tag}"}


def write_team(exp: Experiment, out: Path, *, scenario: str, run_id: str, connect: str | None, overrides: Sequence[str] = (),
               seed: int | None = None) -> Path:
    """Write ``out/team.json`` and, in ``out/team/``, each agent's slice, the plant's slice
    (``plant.pkl``) and the built experiment (``experiment.pkl``) for a team of ``exp``
    whose processes are clients of the router at ``connect`` (None: peers, each given its
    endpoints on its command line): what ``rse agent --id I``, ``rse plant`` and ``rse
    monitor`` read with ``--team out/team.json`` (as after ``rse run``). Returns the team file."""
    import json
    import pickle

    from agents.middleware import make_channel, make_nodes
    from agents.net.config import RunConfig
    from agents.net.launcher import Team
    from agents.net.slices import agent_slices, plant_slice, write_slices

    out = Path(out)
    write_slices(out / "team", agent_slices(exp, make_nodes(exp, make_channel(exp))))
    (out / "team" / "plant.pkl").write_bytes(pickle.dumps(plant_slice(exp), protocol=pickle.HIGHEST_PROTOCOL))
    (out / "team" / "experiment.pkl").write_bytes(pickle.dumps(exp, protocol=pickle.HIGHEST_PROTOCOL))
    team = Team(run_id, {}, "client" if connect else "peer", (connect,) if connect else (), scenario, tuple(overrides),
                seed, RunConfig())
    path = out / "team.json"
    path.write_text(json.dumps(team.as_dict(), indent=1))
    return path


def default_run_id(name: str) -> str:
    """The run id of a compose file: the scenario's run name made key-safe (``mitra_cells``)."""
    stem = "".join(c if c.isascii() and (c.isalnum() or c in "_.-") else "-" for c in name)[:64].strip("-_.")
    return stem or "run"


def _rel(path: Path, base: Path) -> str:
    """``path`` as compose reads it from a file in ``base``: ``./relative`` when possible."""
    try:
        rel = os.path.relpath(path.resolve(), base.resolve())
    except ValueError:  # another drive (Windows)
        return path.resolve().as_posix()
    rel = Path(rel).as_posix()
    return rel if rel.startswith("../") else f"./{rel}"


def _escape(arg: str) -> str:
    """Compose interpolates ``$VAR`` in commands: keep a literal ``$``."""
    return arg.replace("$", "$$")


def secure_mounts(secure: Path, identity: str, base: Path, extra: Sequence[str] = ()) -> list[str]:
    """The read-only mounts of ``identity``'s credentials: ``ca.pem``, ``IDENTITY.pem``,
    ``IDENTITY.key`` (and the files ``extra``) from ``secure`` at ``/certs``.

    Raises
    ------
    ScenarioError
        A file is missing (named, with the command that writes it).
    """
    names = ["ca.pem", f"{identity}.pem", f"{identity}.key", *extra]
    for name in names:
        if not (secure / name).is_file():
            raise ScenarioError(f"--secure {secure}: no {name} (write the credentials with "
                                f"`rse certs {secure} --scenario SCENARIO`)")
    return [Quoted(f"{_rel(secure / name, base)}:{CERTS_DIR}/{name}:ro") for name in names]


def compose_spec(scenario: Path, agent_ids: Sequence[int], *, base: Path, run_id: str,
                 image: str = DEFAULT_IMAGE, secure: Path | None = None, overrides: Sequence[str] = (),
                 seed: int | None = None, peers: bool = False) -> dict[str, Any]:
    """The docker-compose document (a dict) for a team of ``scenario``.

    Parameters
    ----------
    scenario : Path
        The scenario file (mounted read-only into the one-shot service ``team`` only).
    agent_ids : sequence of int
        The scenario's agent ids: one service ``agent-{i}`` each.
    base : Path
        The directory of the compose file: host paths are written relative to it.
    run_id : str
        The run id every service is given (one run, one Rerun recording).
    image : str
        The full image (the service ``team``); the router, the plant and the agents run its
        ``-agent`` sibling, the monitor its ``-monitor`` sibling (:func:`role_images`).
    secure : Path, optional
        A directory written by ``rse certs``: TLS with one identity per service.
    overrides, seed
        ``--set KEY=VALUE`` and ``--seed`` given to ``team``, which builds the experiment.
    peers : bool
        With ``secure``: secure peers, no router (:func:`_peer_args`).

    Returns
    -------
    dict
        ``{"services": {...}, "volumes": {"runs": {}, "team": {}}}``.
    """
    target = f"{SCENARIO_DIR}/{scenario.name}"
    images = role_images(image)
    scenario_mount = Quoted(f"{_rel(scenario, base)}:{target}:ro")
    team_mount = Quoted(f"team:{TEAM_DIR}:ro")
    connect = f"tcp/{ROUTER_HOST}:{ROUTER_PORT}"
    options: list[str] = []
    for ov in overrides:
        options += ["--set", _escape(ov)]
    if seed is not None:
        options += ["--seed", str(seed)]
    # every process of the team starts from its part of the team directory (no scenario, no design)
    common = ["--team", f"{TEAM_DIR}/team.json", "--run-id", run_id, "--client", "--connect", connect]
    after = {"router": {"condition": "service_healthy"}, "team": {"condition": "service_completed_successfully"}}
    names = ["plant", "monitor", *(f"agent-{i}" for i in agent_ids)]
    if peers:
        if secure is None:
            raise ScenarioError("--peers is a team of secure peers: give --secure DIR too")
        common = ["--team", f"{TEAM_DIR}/team.json", "--run-id", run_id]
        del after["router"]

    def role(command: list[str], identity: str, img: str, mounts: list[Any]) -> dict[str, Any]:
        svc: dict[str, Any] = {"image": img, "init": True}
        args = list(command) + (_peer_args(identity, names) if peers else [])
        volumes = list(mounts)
        if secure is not None:
            args += ["--secure", CERTS_DIR, "--identity", identity]
            team_pems = [f"{x}.pem" for x in names if x != identity] if peers else []
            volumes += secure_mounts(secure, identity, base, extra=team_pems)
        svc["command"] = Flow(args)
        svc["volumes"] = volumes
        svc["depends_on"] = {k: dict(v) for k, v in after.items()}
        svc["healthcheck"] = {"test": Flow(HEALTHCHECK), **CLIENT_HEALTH}
        return svc

    router_cmd = ["router", "--listen", f"tcp/0.0.0.0:{ROUTER_PORT}"]
    router: dict[str, Any] = {"image": images["agent"], "init": True}
    if secure is not None:
        router_cmd += ["--secure", CERTS_DIR, "--run-id", run_id]
    router["command"] = Flow(router_cmd)
    if secure is not None and not peers:
        router["volumes"] = secure_mounts(secure, "router", base, extra=[f"agent-{i}.pem" for i in agent_ids])
    router["ports"] = [Quoted(f"{ROUTER_PORT}:{ROUTER_PORT}")]
    router["healthcheck"] = {"test": Flow(HEALTHCHECK), "interval": "2s", "timeout": "10s", "retries": 15}
    router["restart"] = "unless-stopped"

    services: dict[str, Any] = {} if peers else {"router": router}
    # the design once, for every process: the volume "team" (at /runs here: a directory of the image owned by rse)
    services["team"] = {"image": images["full"], "init": True,
                        "command": Flow(["compose", target, "--run-id", run_id, "--write-team", RUNS_DIR, *options,
                                         *(["--peers"] if peers else [])]),
                        "volumes": [scenario_mount, Quoted(f"team:{RUNS_DIR}")], "restart": "no"}
    services["plant"] = role(["plant", *common], "plant", images["agent"], [team_mount])
    monitor = role(["monitor", *common, "--out", f"{RUNS_DIR}/{run_id}", "--serve-web",
                    "--web-port", str(WEB_PORT), "--grpc-port", str(GRPC_PORT)], "monitor", images["monitor"],
                   [team_mount, Quoted(f"runs:{RUNS_DIR}")])
    monitor["ports"] = [Quoted(f"{WEB_PORT}:{WEB_PORT}"), Quoted(f"{GRPC_PORT}:{GRPC_PORT}")]
    services["monitor"] = monitor
    for i in agent_ids:
        svc = role(["agent", "--id", str(i), *common], f"agent-{i}", images["agent"], [team_mount])
        svc["restart"] = "on-failure"
        services[f"agent-{i}"] = svc
    return {"services": services, "volumes": {"runs": {}, "team": {}}}


def _peer_args(identity: str, names: Sequence[str]) -> list[str]:
    """A secure peer's endpoints in a compose file: it listens on ``tls/0.0.0.0:7450`` and
    links to each later service of ``names`` (plant, monitor, agents) by its name, so that
    every pair is linked once and nobody forwards for another (gossip off)."""
    later = list(names)[list(names).index(identity) + 1:]
    out = ["--listen", f"tls/0.0.0.0:{PEER_PORT}"]
    for other in later:
        out += ["--connect", f"tls/{other}:{PEER_PORT}"]
    return out


def command_line(scenario: Path, out: str, *, base: Path, run_id: str, default_run: str, image: str,
                 secure: Path | None, overrides: Sequence[str], seed: int | None, peers: bool = False) -> str:
    """The ``rse compose`` command that writes this file, run from its directory."""
    args = ["rse", "compose", _rel(scenario, base).removeprefix("./"), "-o", out]
    if image != DEFAULT_IMAGE:
        args += ["--image", image]
    if run_id != default_run:
        args += ["--run-id", run_id]
    if secure is not None:
        args += ["--secure", _rel(secure, base).removeprefix("./")]
    if peers:
        args += ["--peers"]
    for ov in overrides:
        args += ["--set", ov]
    if seed is not None:
        args += ["--seed", str(seed)]
    return shlex.join(args)


def render(spec: dict[str, Any], header: Sequence[str] = ()) -> str:
    """The YAML text of ``spec`` (PyYAML), after ``header`` as comment lines."""
    try:
        import yaml
    except ImportError:
        raise ScenarioError("rse compose needs PyYAML: pip install pyyaml") from None

    class Dumper(yaml.SafeDumper):
        def ignore_aliases(self, data: Any) -> bool:  # no &anchors / *aliases: every service in full
            return True

    Dumper.add_representer(Quoted, lambda d, s: d.represent_scalar("tag:yaml.org,2002:str", str(s), style='"'))
    Dumper.add_representer(Flow, lambda d, s: d.represent_sequence("tag:yaml.org,2002:seq", list(s), flow_style=True))
    body = yaml.dump(spec, Dumper=Dumper, sort_keys=False, default_flow_style=False, width=10_000, allow_unicode=True)
    return "".join(f"# {line}\n".replace("# \n", "#\n") for line in header) + body


DASK_PORT = 8786  # the Dask scheduler (rse sweep / rse boundary --cluster tcp://HOST:8786)
DASK_SCHEDULER = "dask-scheduler"


def dask_services(workers: int, *, image: str = DEFAULT_IMAGE) -> dict[str, Any]:
    """Services of a Dask cluster for ``rse sweep --cluster``: ``dask-scheduler`` (port
    8786 published) and ``dask-worker`` (``workers`` replicas, one single-threaded worker
    process each), from ``image``, which must hold the ``cluster`` extra. Workers need no
    scenario file: every task carries its scenario as data."""
    if workers < 1:
        raise ScenarioError(f"--dask-workers: expected at least 1 worker, got {workers}")
    blas = {v: "1" for v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    scheduler = {"image": image, "init": True, "entrypoint": Flow(["dask", "scheduler"]),
                 "command": Flow(["--host", "0.0.0.0", "--port", str(DASK_PORT), "--no-dashboard"]),
                 "ports": [Quoted(f"{DASK_PORT}:{DASK_PORT}")], "restart": "unless-stopped"}
    worker = {"image": image, "init": True, "entrypoint": Flow(["dask", "worker"]),
              "command": Flow([f"tcp://{DASK_SCHEDULER}:{DASK_PORT}", "--nthreads", "1", "--no-dashboard"]),
              "environment": blas, "depends_on": [DASK_SCHEDULER], "deploy": {"replicas": int(workers)},
              "restart": "on-failure"}
    return {DASK_SCHEDULER: scheduler, "dask-worker": worker}
