"""What an algorithm plugin builds on: the public helpers of the scenario layer.

A plugin module (built in, or from another package through the ``rse.algorithms`` entry
point group, see :mod:`scenarios.plugins` and ``docs/algorithms/writing-a-plugin.md``)
imports from here, at module level: this module imports neither the schema nor the
builder, which are still being imported when the plugins are loaded.

* :func:`matrix`: a checked matrix from a scenario's list of rows;
* :func:`explicit_AB`: ``[plant] A`` and ``B``, checked;
* :func:`init_vector`: an initial vector from an ``Init`` table (``x0 = {kind = ...}``);
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
    "init_vector", "matrix", "rng_for",
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
