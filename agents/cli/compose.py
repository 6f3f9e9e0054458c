"""``rse compose``: a docker-compose file running a scenario's team in containers.

Added to the group in :mod:`agents.cli`. Exit statuses
as there: 0 success, 1 failure (e.g. the file cannot be written), 2 bad input (scenario,
``--set``, ``--run-id``, ``--image``, missing credentials under ``--secure``).
"""

from __future__ import annotations

import re
from pathlib import Path

import click

from estimation.errors import ScenarioError

from .common import handle_errors, load_experiment, scenario_options

_IMAGE_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._/:@-]*\Z")


@click.command()
@scenario_options
@click.option("-o", "--output", "output", default="docker-compose.yml", show_default=True, metavar="FILE",
              help="Where to write the compose file ('-': standard output; host paths are then relative to the "
                   "current directory).")
@click.option("--image", default=None, metavar="NAME[:TAG]",
              help="The full image (the one-shot design, team), built from the repository's Dockerfile; the "
                   "router, the plant and the agents run NAME-agent[:TAG], the monitor NAME-monitor[:TAG], its "
                   "targets agent and monitor (default: resilient-state-estimation:latest).")
@click.option("--run-id", default=None,
              help="The run id every service is given (one run, one Rerun recording; the monitor writes "
                   "/runs/RUN_ID). Default: the scenario's run name.")
@click.option("--secure", type=click.Path(path_type=Path), default=None, metavar="DIR",
              help="Credentials written by `rse certs DIR --scenario SCENARIO`: mutual TLS and the router's "
                   "access control; each service mounts only ca.pem and its own certificate and key.")
@click.option("--peers", is_flag=True,
              help="With --secure: secure peers, no router (each service listens on tls/0.0.0.0:7450 and links to "
                   "the others by name; it also mounts the team's certificates).")
@click.option("--dask-workers", type=click.IntRange(min=0), default=0, show_default=True, metavar="N",
              help="Also add a Dask scheduler (port 8786) and N Dask workers for `rse sweep --cluster "
                   "tcp://HOST:8786` (the image needs the cluster extra).")
@click.option("--write-team", type=click.Path(file_okay=False, path_type=Path), default=None, metavar="DIR",
              help="Instead of a compose file: build the experiment once and write DIR/team.json, each agent's "
                   "slice, the plant's and the built experiment (DIR/team/): what `rse agent --id I`, `rse plant` "
                   "and `rse monitor` read with --team DIR/team.json (the compose file's one-shot service team "
                   "runs this).")
@handle_errors
def compose(scenario: Path, overrides: tuple[str, ...], seed: int | None, output: str, image: str | None,
            run_id: str | None, secure: Path | None, peers: bool, dask_workers: int, write_team: Path | None) -> None:
    """Write a docker-compose file running SCENARIO as a team of containers.

    Services: router (a Zenoh router, port 7447 published), team (one-shot: reads the
    scenario file mounted read-only, computes the offline design once and writes each
    process's slice to the volume `team`), plant, monitor (the run directory in the volume
    `runs`, the Rerun web viewer on ports 9090 and 9876) and one agent-I per agent of the
    scenario, each a client of the router with the same run id, started from its slice.
    Agents restart on failure and rejoin the running team. Then: build the images
    (docs/deployment.md) and `docker compose up`.
    """
    from transport.keys import validate_run_id

    from ..compose import DEFAULT_IMAGE, GRPC_PORT, ROUTER_HOST, ROUTER_PORT, WEB_PORT, command_line, compose_spec, default_run_id, render
    from ..compose import write_team as write_team_files

    image = image if image is not None else DEFAULT_IMAGE
    if not _IMAGE_RE.match(image):
        raise ScenarioError(f"--image: invalid image name {image!r} (e.g. resilient-state-estimation:latest)")
    if secure is not None and not secure.is_dir():
        raise ScenarioError(f"--secure {secure}: no such directory (write the credentials with "
                            f"`rse certs {secure} --scenario {scenario}`)")
    exp, _ = load_experiment(scenario, overrides, seed)
    default_run = default_run_id(exp.scenario.run.name)
    run_id = run_id if run_id is not None else default_run
    try:
        validate_run_id(run_id)
    except ValueError as exc:
        raise ScenarioError(f"--run-id: {exc}") from None
    if write_team is not None:
        team = write_team_files(exp, write_team, scenario=str(scenario), run_id=run_id, overrides=overrides, seed=seed,
                                connect=None if peers else f"tcp/{ROUTER_HOST}:{ROUTER_PORT}")
        click.echo(f"wrote {team} and the slices of {len(exp.agent_ids)} agent(s) in {write_team / 'team'}")
        return
    to_stdout = output == "-"
    path = Path(output)
    base = Path.cwd() if to_stdout else (path.parent if str(path.parent) else Path("."))
    spec = compose_spec(scenario, exp.agent_ids, base=base, run_id=run_id, image=image, secure=secure,
                        overrides=overrides, seed=seed, peers=peers)
    cmd = command_line(scenario, output if to_stdout else path.name, base=base, run_id=run_id,
                       default_run=default_run, image=image, secure=secure, overrides=overrides, seed=seed, peers=peers)
    if dask_workers:
        from ..compose import DASK_PORT, dask_services

        spec["services"].update(dask_services(dask_workers, image=image))
        cmd += f" --dask-workers {dask_workers}"
    header = [
        f"{exp.scenario.run.name}: {'secure peers' if peers else 'router'}, plant, monitor and {len(exp.agent_ids)} "
        f"agents; run id {run_id}.",
        f"Written by `{cmd}`: regenerate it rather than edit it.",
        ("docker build -t resilient-state-estimation . && docker build --target agent -t "
         "resilient-state-estimation-agent . && docker build --target monitor -t "
         "resilient-state-estimation-monitor . && docker compose up   (docs/deployment.md)"),
        f"Rerun web viewer: http://127.0.0.1:{WEB_PORT}/?url=rerun+http://127.0.0.1:{GRPC_PORT}/proxy",
        f"Run directory: the volume 'runs', /runs/{run_id} in the monitor "
        f"(docker compose cp monitor:/runs/{run_id} runs/).",
    ]
    if dask_workers:
        header.append(f"Dask: docker compose up -d dask-scheduler dask-worker, then rse sweep SCENARIO ... "
                      f"--cluster tcp://127.0.0.1:{DASK_PORT} (docs/sweeps.md).")
    text = render(spec, header)
    if to_stdout:
        click.echo(text, nl=False)
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    n = len(exp.agent_ids)
    click.echo(f"wrote {path}: {'no router (secure peers)' if peers else 'router'}, plant, monitor, {n} agent(s) "
               f"({', '.join(s for s in spec['services'] if s.startswith('agent-'))}); run id {run_id}"
               + ("; TLS identities from " + str(secure) if secure is not None else "")
               + (f"; Dask scheduler and {dask_workers} worker(s)" if dask_workers else ""))
