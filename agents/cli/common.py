"""What every ``rse`` command shares: the error handling (one-line messages and exit
statuses, :mod:`estimation.errors`), the common flags and the scenario loader.

Command modules import from here, never from the group module (:mod:`agents.cli`).
"""

from __future__ import annotations

import functools
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from agents.net.exits import EXIT_BAD_INPUT, EXIT_EXPECTATION, EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK, describe, exit_status
from estimation.errors import RSEError, ScenarioError

from ..api import beyond_threat_model, load_experiment

if TYPE_CHECKING:
    from scenarios.build import Experiment

__all__ = [
    "EXIT_OK", "EXIT_FAILED", "EXIT_BAD_INPUT", "EXIT_EXPECTATION", "EXIT_INTERRUPTED",
    "handle_errors", "scenario_options", "rerun_options", "dashboard_options", "wait_while_serving",
    "load_experiment", "secure_files", "sigterm_interrupts", "warn_threat_model",
]


def warn_threat_model(exp: Experiment) -> None:
    """One warning line on stderr when the scenario's attacks exceed its threat model."""
    line = beyond_threat_model(exp)
    if line is not None:
        from rich.markup import escape

        from ..console import err

        err.print(f"[yellow]warning:[/yellow] {escape(line)}", soft_wrap=True)


def handle_errors(fn: Callable) -> Callable:
    """Turn the runtime's own errors into a one-line message and an exit status
    (:func:`agents.net.exits.exit_status`); a bug is an internal error, its traceback only
    with ``RSE_DEBUG=1``."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        from ..console import error

        try:
            return fn(*args, **kwargs)
        except (RSEError, KeyboardInterrupt, OSError) as exc:
            error(describe(exc))
            sys.exit(exit_status(exc))
        except Exception as exc:  # a bug: say so plainly, traceback only on request
            interrupt = _interrupt_within(exc)
            if interrupt is not None:  # a Ctrl-C that Python wrapped (e.g. RuntimeError of __set_name__ in an import)
                error(describe(interrupt))
                sys.exit(exit_status(interrupt))
            if os.environ.get("RSE_DEBUG"):
                raise
            error(describe(exc))
            sys.exit(EXIT_FAILED)

    return wrapper


def _interrupt_within(exc: BaseException) -> KeyboardInterrupt | None:
    """The KeyboardInterrupt that caused ``exc``, if any (its cause / context chain)."""
    seen = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return e
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return None


def scenario_options(fn: Callable) -> Callable:
    """The flags every scenario-taking sub-command shares."""
    fn = click.option("--set", "overrides", multiple=True, metavar="KEY.PATH=VALUE",
                      help="Override any scenario key (TOML value), e.g. --set estimator.kappa=5. Repeatable.")(fn)
    fn = click.option("--seed", type=click.IntRange(min=0), default=None, help="Override run.seed.")(fn)
    fn = click.argument("scenario", type=click.Path(dir_okay=False, path_type=Path))(fn)
    return fn


def rerun_options(fn: Callable) -> Callable:
    """The Rerun sink flags every run command shares."""
    fn = click.option("--grpc-port", type=click.IntRange(1, 65535), default=None,
                      help="Port of the gRPC server the web viewer reads from (default 9876).")(fn)
    fn = click.option("--web-port", type=click.IntRange(1, 65535), default=None,
                      help="Port of the web viewer (default 9090).")(fn)
    fn = click.option("--serve-web", is_flag=True, help="Serve the web viewer so a browser (also on another machine) can watch live; the URL is printed.")(fn)
    fn = click.option("--viewer", is_flag=True, help="Spawn the native Rerun viewer (needs a display).")(fn)
    fn = click.option("--no-rerun", is_flag=True, help="No Rerun output at all (benchmarks).")(fn)
    fn = click.option("--rrd", type=click.Path(dir_okay=False, path_type=Path), default=None,
                      help="Recording file (default: recording.rrd in the run directory).")(fn)
    return fn


def dashboard_options(run_dir: Path, rrd: Path | None, no_rerun: bool, viewer: bool, serve_web: bool,
                      web_port: int | None, grpc_port: int | None):
    from ..dashboard import DashboardOptions

    if no_rerun:
        if viewer or serve_web or rrd:
            raise ScenarioError("--no-rerun cannot be combined with --rrd, --viewer or --serve-web", source="command line")
        return None
    return DashboardOptions(rrd=rrd or run_dir / "recording.rrd", viewer=viewer, serve_web=serve_web,
                            web_port=web_port, grpc_port=grpc_port)


def sigterm_interrupts() -> None:
    """SIGTERM interrupts this command as Ctrl-C does (a ``KeyboardInterrupt`` naming the
    signal), so that it ends through the same paths: files completed, sinks closed, exit 130."""
    import signal
    import threading

    def handler(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt(signal.Signals(signum).name)

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, handler)
        # also when started with SIGINT ignored (a background job of a script): a signal
        # sent on purpose stops the command
        signal.signal(signal.SIGINT, signal.default_int_handler)


def wait_while_serving(url: str) -> None:
    """After a run with --serve-web: keep the viewer up until Ctrl-C / SIGTERM."""
    import signal
    import time

    from ..console import out as console

    # the handler only notes the signal (Event.set() in a handler can deadlock with the
    # main thread's Event.wait(): agents.net.router.serve)
    signalled: list[int] = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, _frame: signalled.append(signum))
    console.print(f"the run is finished; still serving the recording at {url} (Ctrl-C to stop)")
    while not signalled:
        time.sleep(0.1)


def secure_files(directory: Path, identity: str):
    """:class:`transport.secure.TlsFiles` of ``identity`` in ``directory``; a missing or
    unreadable file is a :class:`ScenarioError` (exit status 2) naming it."""
    from transport.secure import tls_files

    try:
        return tls_files(directory, identity)
    except ValueError as exc:
        raise ScenarioError(str(exc)) from None


def warn_plain(endpoints: Any, secure: Any) -> None:
    """One line on stderr when a plain (not ``--secure``) process uses an endpoint off this
    host: plain mode authenticates nobody."""
    from transport.zenoh_session import is_loopback

    if secure is not None:
        return
    remote = [e for e in endpoints if e and not is_loopback(e)]
    if remote:
        from ..console import err

        err.print(f"warning: plain mode authenticates nobody: whoever reaches {remote[0]} can join and speak for "
                  "any process (--secure DIR: see docs/deployment.md)", soft_wrap=True)


def sign_dir(directory: Path | None) -> str | None:
    """``--sign DIR``: the directory of the team's signing keys, checked to hold some
    (``*.sig.pub``; each agent then loads its own key); None without the flag."""
    if directory is None:
        return None
    from transport.signing import load_public_keys

    try:
        load_public_keys(directory)
    except (ValueError, ImportError) as exc:
        raise ScenarioError(f"--sign: {exc}") from None
    return str(Path(directory).resolve())
