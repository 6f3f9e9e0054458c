"""``rse verify-evidence``: check equivocation evidence offline with the team's public keys."""

from __future__ import annotations

from pathlib import Path

import click

from estimation.errors import RSEError, ScenarioError

from .common import handle_errors


@click.command("verify-evidence")
@click.argument("file", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--certs", "certs", required=True, type=click.Path(file_okay=False, path_type=Path), metavar="DIR",
              help="The team's keys (`rse certs DIR`): the *.sig.pub public keys are read.")
@handle_errors
def verify_evidence(file: Path, certs: Path) -> None:
    """Check every record of FILE (evidence.jsonl): two messages of one sender, run and stamp
    with different values, both signed with the sender's key. Exit 0 if every record proves
    its conviction, 1 if one does not (each failure named)."""
    from transport.signing import load_public_keys

    from ..console import out as console
    from ..evidence import verify_file

    try:
        keys = load_public_keys(certs)
    except ValueError as exc:
        raise ScenarioError(str(exc)) from None
    if not file.is_file():
        raise ScenarioError(f"{file}: no such evidence file")
    results = verify_file(file, keys)
    bad = [(n, why) for n, _rec, why in results if why is not None]
    for n, rec, why in results:
        if why is None and rec is not None:
            console.print(f"{file}:{n}: verified: agent {rec['sender']} equivocated at stamp {rec['stamp']} "
                          f"(receivers {rec['told'][0]} and {rec['told'][1]}), convicted at round {rec['convicted_at']}")
        else:
            console.print(f"{file}:{n}: NOT verified: {why}")
    if not results:
        raise RSEError(f"{file}: no evidence record")
    if bad:
        raise RSEError(f"{len(bad)} of {len(results)} evidence record(s) do not verify: "
                       + "; ".join(f"line {n}: {why}" for n, why in bad))
