"""Shared building blocks of the scenario schema (used by :mod:`scenarios.schema` and the
algorithm plugins in :mod:`scenarios.plugins`)."""

from __future__ import annotations

from typing import Annotated, Literal, Protocol

from pydantic import BaseModel, ConfigDict, Field, model_validator


class Strict(BaseModel):
    """A table of the scenario format: unknown keys are errors, and so is every NaN or
    infinite number (a plugin's ``[estimator]`` section inherits both)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class EstimatorTable(Protocol):
    """What every plugin's ``[estimator]`` table has (its ``ESTIMATOR`` model): the
    algorithm's name, a one-value ``Literal``. The scenario's ``estimator`` is the union of
    the registered plugins' models, known at run time only; this is its static type."""

    @property
    def algorithm(self) -> str: ...


Matrix = list[list[float]]
Vector = list[float]


class UniformInit(Strict):
    kind: Literal["uniform"] = "uniform"
    low: float = -1.0
    high: float = 1.0

    @model_validator(mode="after")
    def _order(self) -> "UniformInit":
        if not self.low <= self.high:
            raise ValueError(f"low must be <= high, got low={self.low}, high={self.high}")
        return self


class ValueInit(Strict):
    kind: Literal["value"] = "value"
    value: Vector


class ZeroInit(Strict):
    kind: Literal["zero"] = "zero"


Init = Annotated[UniformInit | ValueInit | ZeroInit, Field(discriminator="kind")]
