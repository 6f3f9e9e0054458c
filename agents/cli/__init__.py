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
from .compose import compose
from .deploy import certs, router
from .net import agent, monitor, plant, run
from .redteam import redteam
from .report import report
from .sim import check, simulate
from .sweep import sweep

__all__ = ["cli", "main"]


@click.group(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(package_name="resilient-state-estimation", prog_name="rse")
def cli() -> None:
    """Resilient distributed state estimation: simulate, run and check scenarios."""


for _command in (simulate, check, run, plant, agent, monitor, router, certs, compose, report, sweep, boundary, redteam,
                 bench):
    cli.add_command(_command)


def main() -> None:
    """The ``rse`` console script: pins BLAS to one thread (the runtime's linear algebra is
    many small products; users can override the variables), then runs the command."""
    from ..api import pin_blas_threads

    pin_blas_threads()
    cli(prog_name="rse")
