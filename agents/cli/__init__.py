"""The ``rse`` command line: a package whose command groups are modules.

``python -m agents.cli --help`` (or ``rse --help``) lists every command. Each command
module imports the shared flags and the error handling from :mod:`agents.cli.common` and
the library through :mod:`agents.api`; nothing outside this package imports it.

Exit status (:mod:`estimation.errors`): 0 success; 1 a condition (``rse check``) or the
run itself failed; 2 bad input (usage, scenario file, ``--set``); 3 the run finished but
an ``[[expect]]`` bound of the scenario failed; 130 interrupted.
"""

from __future__ import annotations

import click

from .bench import bench
from .boundary import boundary
from .chaos import chaos
from .compose import compose
from .deploy import certs, router
from .evidence import verify_evidence
from .net import agent, monitor, plant, run
from .redteam import redteam
from .replay import replay
from .report import report
from .sim import check, simulate
from .sweep import sweep

__all__ = ["cli", "main"]


@click.group(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(package_name="resilient-state-estimation", prog_name="rse")
def cli() -> None:
    """Resilient distributed state estimation: simulate, run and check scenarios."""


for _command in (simulate, check, run, plant, agent, monitor, router, certs, compose, report, sweep, boundary, redteam,
                 bench, replay, verify_evidence, chaos):
    cli.add_command(_command)


def main() -> None:
    """The ``rse`` console script: pins BLAS to one thread (the runtime's linear algebra is
    many small products; users can override the variables), then runs the command.

    When the command is over (also after Ctrl-C / SIGTERM: every command closes its own
    sessions, sinks and child processes on the way out), the exit handlers run, the output
    is flushed and the process exits at once: the interpreter's teardown of numpy, scipy,
    pyarrow and rerun takes seconds on a loaded machine, and a command must end within
    2 s of a signal."""
    import atexit
    import os
    import sys

    from ..api import pin_blas_threads

    pin_blas_threads()
    try:
        cli(prog_name="rse")
        code = 0
    except SystemExit as exc:
        if exc.code is None or isinstance(exc.code, int):
            code = exc.code or 0
        else:
            print(exc.code, file=sys.stderr)
            code = 1
    except KeyboardInterrupt:  # a signal outside a command's own handling (while click dispatches)
        print("error: interrupted", file=sys.stderr)
        code = 130
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(code)
