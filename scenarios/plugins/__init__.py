"""Algorithm plugins: one module per paper's estimator (and the named plants it brings).

A plugin module defines:

* ``ESTIMATOR``: the pydantic model of its ``[estimator]`` table (a ``Strict`` subclass
  whose ``algorithm`` field is a one-value ``Literal``);
* ``PLANTS``: optional ``{model name: (default params, build(scenario, source) -> PlantModel)}``
  for the named plants it brings (``[plant] model = ...``);
* ``design(exp, *, check) -> object``: the offline design, done once per run
  (``exp.design`` holds it); raise :class:`~estimation.errors.ScenarioError` naming the key;
* ``make_estimator(exp, i)``: a fresh estimator for agent index ``i``;
* ``conditions(exp) -> list[Condition]``: what ``rse check`` prints;
* ``design_json(exp) -> dict``: the design as written to ``design.json``.
* ``graph_conditions(exp) -> list[Condition]``: optional; replaces the generic
  connectivity lines of ``rse check`` (e.g. for an algorithm made for directed graphs).

To add an algorithm, write its module and add its name to :data:`MODULES`.
"""

from __future__ import annotations

import importlib
from functools import lru_cache
from types import ModuleType

MODULES = (
    "scenarios.plugins.lee_kim_shim",
    "scenarios.plugins.mitra",
    "scenarios.plugins.mao_tabuada",
    "scenarios.plugins.ugrinovskii",
    "scenarios.plugins.inverters",
)


@lru_cache(maxsize=None)
def modules() -> tuple[ModuleType, ...]:
    return tuple(importlib.import_module(m) for m in MODULES)


def estimator_sections() -> tuple[type, ...]:
    return tuple(m.ESTIMATOR for m in modules())


def plant_model_names() -> tuple[str, ...]:
    return tuple(name for m in modules() for name in getattr(m, "PLANTS", {}))


def algorithm(name: str) -> ModuleType:
    """The plugin whose ``ESTIMATOR`` has ``algorithm = name``."""
    for m in modules():
        if m.ESTIMATOR.model_fields["algorithm"].annotation.__args__[0] == name:
            return m
    raise KeyError(name)


def plant(name: str):
    """``(defaults, build)`` of a plugin's named plant."""
    for m in modules():
        if name in getattr(m, "PLANTS", {}):
            return m.PLANTS[name]
    raise KeyError(name)
