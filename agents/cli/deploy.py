"""The deployment commands of ``rse``: ``router`` (a Zenoh router) and ``certs`` (TLS identities).

Added to the group in :mod:`agents.cli`. Exit statuses
as there: 0 success (``rse router`` also after Ctrl-C / SIGTERM), 1 failure, 2 bad input.
"""

from __future__ import annotations

from pathlib import Path

import click

from estimation.errors import ScenarioError

from .common import handle_errors, secure_files


@click.command()
@click.option("--listen", multiple=True, metavar="tcp/HOST:PORT",
              help="Endpoint to listen on (repeatable; port 0: a free port). Default: the --config file's, "
                   "else tcp/0.0.0.0:7447 (every interface, as a container needs; tcp/127.0.0.1:7447 for this host only).")
@click.option("--config", "config_file", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="A Zenoh configuration file (JSON5) loaded first; mode, listen, scouting and --secure's settings go on top.")
@click.option("--secure", type=click.Path(file_okay=False, path_type=Path), default=None, metavar="DIR",
              help="TLS with mutual authentication and access control, certificates from `rse certs DIR` "
                   "(ca.pem, router.pem, router.key; the agents admitted are those of DIR/agent-I.pem).")
@click.option("--run-id", default=None, help="With --secure: admit this run only (default: any run).")
@handle_errors
def router(listen: tuple[str, ...], config_file: Path | None, secure: Path | None, run_id: str | None) -> None:
    """Run a Zenoh router in this process until Ctrl-C / SIGTERM.

    Plant, monitor and agents on any host then join as its clients:
    `rse agent --id 3 SCENARIO --run-id RUN --client --connect tcp/ROUTER_HOST:7447`.
    Scouting is off (clients name the router). Prints the endpoints it listens on.
    """
    from ..net.router import router_config, serve

    files = secure_files(secure, "router") if secure is not None else None
    if run_id is not None and files is None:
        raise ScenarioError("--run-id only applies with --secure (it restricts the access control to one run)")
    conf, eps = router_config(listen, config_file=config_file, secure=files, run_id=run_id or "*")
    if files is not None:
        from transport.secure import agent_ids_in

        ids = agent_ids_in(files.directory)
        click.echo(f"rse router: TLS with mutual authentication (CA {files.ca}); access control for plant, monitor "
                   f"and {len(ids)} agent(s): {_ranges(ids)}")
    serve(conf, eps, say=click.echo)
    click.echo("rse router: stopped")


@click.command()
@click.argument("directory", type=click.Path(file_okay=False, path_type=Path))
@click.option("--scenario", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="One certificate per agent of this scenario (its agent ids).")
@click.option("--agents", type=click.IntRange(1, 10_000), default=None, metavar="N",
              help="One certificate per agent 1..N (instead of --scenario).")
@click.option("--host", "hosts", multiple=True, metavar="NAME",
              help="Also valid for this DNS name or IP address (repeatable): how clients on other hosts name the "
                   "router. Always valid: localhost, 127.0.0.1, ::1 and the identity (router: the compose service).")
@click.option("--days", type=click.IntRange(1, 36500), default=365, show_default=True, help="Validity.")
@click.option("--force", is_flag=True, help="Replace an existing set in DIRECTORY (a new CA: every file changes).")
@handle_errors
def certs(directory: Path, scenario: Path | None, agents: int | None, hosts: tuple[str, ...], days: int,
          force: bool) -> None:
    """Write a CA and one TLS certificate and key per process to DIRECTORY (for --secure).

    Files: ca.pem; router, plant, monitor and agent-I (each agent id) .pem and .key, the
    common name being that identity; keys are mode 0600. The CA's private key is not kept
    (to add an agent, write the set again with --force and hand out the new files).
    """
    if (scenario is None) == (agents is None):
        raise ScenarioError("give exactly one of --scenario SCENARIO or --agents N")
    if agents is not None:
        ids = list(range(1, agents + 1))
    elif scenario is not None:
        from .common import load_experiment

        exp, _ = load_experiment(scenario, (), None, check_conditions=False)
        ids = list(exp.agent_ids)
    from transport.certs import write_certs

    identities = ["router", "plant", "monitor", *(f"agent-{i}" for i in ids)]
    try:
        written = write_certs(directory, identities, hosts=hosts, days=days, force=force)
    except ValueError as exc:
        raise ScenarioError(str(exc)) from None
    except OSError as exc:  # not a directory, not writable, disk full, ...
        raise ScenarioError(f"cannot write certificates to {directory}: {exc.strerror or exc}"
                            + (f" ({exc.filename})" if exc.filename and str(exc.filename) != str(directory) else "")) from None
    except ImportError as exc:
        from estimation.errors import RSEError

        raise RSEError(str(exc)) from None
    click.echo(f"rse certs: {len(written)} files in {directory}: ca.pem and the certificates and keys of router, "
               f"plant, monitor and agent(s) {_ranges(ids)}, and their Ed25519 signing keys (*.sig.key, *.sig.pub)")


def _ranges(ids: list[int]) -> str:
    """``[1, 2, 3, 5]`` -> ``"1-3, 5"``."""
    spans: list[list[int]] = []
    for i in ids:
        if spans and spans[-1][1] == i - 1:
            spans[-1][1] = i
        else:
            spans.append([i, i])
    return ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in spans)
