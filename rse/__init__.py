"""``import rse``: the public Python API of the runtime (a facade over :mod:`agents.api`).

See :mod:`agents.api` for the functions: :func:`load`, :func:`simulate`, :func:`run_team`,
:func:`check`, :func:`beyond_threat_model`, :func:`sweep`, :func:`boundary`, :func:`open_run`, :func:`replay`, :func:`chaos` and the
:class:`RunResult` they return.
"""

from agents.api import RunResult, beyond_threat_model, boundary, chaos, check, load, open_run, pin_blas_threads, replay, run_team, simulate, sweep

__all__ = ["load", "simulate", "run_team", "check", "beyond_threat_model", "sweep", "boundary", "open_run", "RunResult", "pin_blas_threads",
           "replay", "chaos"]
