"""``rse chaos``: a seeded soak of faults against a realtime team (docs/chaos.md).

:mod:`~agents.chaos.schedule` plans the faults (pure data), :mod:`~agents.chaos.inject`
injects them into a running team, :mod:`~agents.chaos.measure` measures each one from the
run directory, :mod:`~agents.chaos.runner` composes the three (:func:`run_chaos`).
"""

from .runner import ChaosResult, chaos_bound, run_chaos
from .schedule import BUDGETS, KINDS, LASTS, Fault, parse_budgets, parse_kinds, plan_faults

__all__ = ["run_chaos", "ChaosResult", "chaos_bound", "plan_faults", "Fault", "KINDS", "BUDGETS", "LASTS",
           "parse_kinds", "parse_budgets"]
