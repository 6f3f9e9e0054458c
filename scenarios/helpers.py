"""What an algorithm plugin builds on: the public helpers of the scenario layer.

A plugin module (built in, or from another package through the ``rse.algorithms`` entry
point group, see :mod:`scenarios.plugins` and ``docs/algorithms/writing-a-plugin.md``)
imports from here, at module level: this module imports neither the schema nor the
builder, which are still being imported when the plugins are loaded.

* :func:`matrix`: a checked matrix from a scenario's list of rows;
* :func:`explicit_AB`: ``[plant] A`` and ``B``, checked;
* :func:`init_vector`: an initial vector from an ``Init`` table (``x0 = {kind = ...}``);
* :func:`plant_params`: ``[plant] params`` over the model's defaults, checked (names,
  finite numbers, integers); :func:`integer` and :func:`finite` for one value;
* :func:`check_size`: a size the scenario asks for (states, agents, substeps) within the
  documented limits (:mod:`scenarios.budget`), before anything of that size is built;
* :func:`rng_for` and the ``STREAM_*`` tags: seeded generators, identical in both drivers;
* :class:`Condition`: one line of ``rse check``; :func:`checked_design`: the design, or its
  failure as a condition;
* :class:`PlantModel`: what a named plant (``PLANTS``) builds;
* :func:`estimator_section`: the ``[estimator]`` table typed as the plugin's own section;
* :class:`ThreatModel`: what the algorithm tolerates (``THREAT_MODEL``, for ``rse redteam``);
* :class:`Strict`, :data:`Init`, :class:`UniformInit`, :class:`ZeroInit`, :data:`Matrix`,
  :data:`Vector`: building blocks of an ``[estimator]`` section.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from estimation.errors import ScenarioError

from . import budget
from .common import (
    STREAM_AGENT_X0,
    STREAM_ESTIMATOR,
    STREAM_PLANT_NOISE,
    Condition,
    PlantModel,
    PlantStepper,
    ThreatModel,
    checked_design,
    estimator_section,
    rng_for,
)
from .types import Init, Matrix, Strict, UniformInit, ValueInit, Vector, ZeroInit

__all__ = [
    "STREAM_AGENT_X0", "STREAM_ESTIMATOR", "STREAM_PLANT_NOISE", "Condition", "Init", "Matrix", "PlantModel",
    "PlantStepper", "Strict", "ThreatModel", "UniformInit", "ValueInit", "Vector", "ZeroInit", "checked_design", "estimator_section", "explicit_AB",
    "init_vector", "matrix", "rng_for", "plant_params", "integer", "finite", "check_size",
]


def init_vector(spec: Init, n: int, rng: np.random.Generator, *, where: str) -> np.ndarray:
    """An initial vector ``(n,)`` from an :data:`~scenarios.types.Init` table (uniform,
    zero or an explicit value); ``where`` is the key path named by an error."""
    if spec.kind == "uniform":
        return rng.uniform(spec.low, spec.high, size=n)
    if spec.kind == "zero":
        return np.zeros(n)
    v = np.asarray(spec.value, dtype=float)
    if v.shape != (n,):
        raise ScenarioError(f"{where}.value: expected {n} numbers (the state dimension), got {len(v)}")
    return v


def matrix(rows: Any, where: str, source: str, *, cols: int | None = None, nrows: int | None = None) -> np.ndarray:
    """A matrix from a scenario's list of rows, checked: rectangular, finite, with ``cols``
    columns and ``nrows`` rows when given. Errors are :class:`ScenarioError` naming
    ``where`` (the key path, e.g. ``"estimator.L"``) in ``source`` (the file)."""
    try:
        M = np.array(rows, dtype=float)
    except ValueError:
        raise ScenarioError(f"{where}: rows have different lengths", source=source) from None
    if M.ndim != 2:
        raise ScenarioError(f"{where}: expected a matrix (list of rows), got shape {M.shape}", source=source)
    if cols is not None and M.shape[1] != cols:
        raise ScenarioError(f"{where}: expected rows of length {cols}, got {M.shape[1]}", source=source)
    if nrows is not None and M.shape[0] != nrows:
        raise ScenarioError(f"{where}: expected {nrows} rows, got {M.shape[0]}", source=source)
    if not np.all(np.isfinite(M)):
        raise ScenarioError(f"{where}: entries must be finite", source=source)
    return M


def explicit_AB(pl: Any, source: str) -> tuple[np.ndarray, np.ndarray]:
    """``[plant] A`` (square, required) and ``B`` (``n`` rows; none: no input), checked."""
    if pl.A is None:
        raise ScenarioError(f"plant.A: required for model = {pl.model!r}", source=source)
    A = matrix(pl.A, "plant.A", source)
    if A.shape[0] != A.shape[1]:
        raise ScenarioError(f"plant.A: expected a square matrix, got shape {A.shape}", source=source)
    n = A.shape[0]
    B = matrix(pl.B, "plant.B", source, nrows=n) if pl.B is not None else np.zeros((n, 0))
    return A, B


def finite(value: Any, where: str, source: str | None) -> float:
    """``value`` as a finite float; else a :class:`ScenarioError` naming ``where``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ScenarioError(f"{where}: expected a number, got {value!r}", source=source)
    if not np.isfinite(value):
        raise ScenarioError(f"{where}: expected a finite number, got {value!r}", source=source)
    return float(value)


def integer(value: Any, where: str, source: str | None, *, low: int | None = 1, high: int | None = None) -> int:
    """``value`` (an int, or a float with no fractional part) as an int in ``[low, high]``;
    else a :class:`ScenarioError` naming ``where``. Checked before any ``int()``: NaN,
    infinity and 1e300 are refused here, not where they are used."""
    v = finite(value, where, source)
    if v != int(v):
        raise ScenarioError(f"{where}: expected an integer, got {value!r}", source=source)
    if low is not None and v < low:
        raise ScenarioError(f"{where}: expected an integer >= {low}, got {value!r}", source=source)
    if high is not None and v > high:
        raise ScenarioError(f"{where}: expected an integer <= {high}, got {value!r}", source=source)
    return int(v)


def plant_params(pl: Any, defaults: dict[str, float], source: str | None, *,
                 integers: dict[str, tuple[int | None, int | None]] | None = None) -> dict[str, Any]:
    """``[plant] params`` over a named model's ``defaults``: unknown names refused, every
    value finite, each key of ``integers`` (``{name: (low, high)}``, None: unbounded) an
    integer in its range (returned as int)."""
    unknown = set(pl.params) - set(defaults)
    if unknown:
        raise ScenarioError(f"plant.params: unknown parameter(s) {sorted(unknown)}; expected some of {sorted(defaults)}",
                            source=source)
    p: dict[str, Any] = {k: finite(v, f"plant.params.{k}", source) for k, v in {**defaults, **pl.params}.items()}
    for key, (low, high) in (integers or {}).items():
        if key in p:
            p[key] = integer(p[key], f"plant.params.{key}", source, low=low, high=high)
    return p


def check_size(what: str, value: float, keys: str, *, run: Any, source: str | None) -> None:
    """Refuse a count of ``what`` (``"states"``, ``"agents"``, ``"substeps"``) beyond the
    documented limit (:data:`scenarios.budget.LIMITS`) unless ``run.force``; ``keys``
    names the scenario keys that set it, e.g. ``"plant.params.K x plant.params.states"``."""
    force = bool(getattr(run, "force", False))
    budget.check_count(what, value, keys, force=force, source=source)
    if what == "states":  # the plant's dense n x n matrices must fit before they are built
        budget.check_run(budget.Cost(memory=24.0 * float(value) ** 2, seconds=0.0), keys, force=force, source=source)
