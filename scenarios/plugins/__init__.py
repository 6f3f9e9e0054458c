"""Algorithm plugins: one module per algorithm (and the named plants it brings).

Plugins are the built-in modules of :data:`MODULES` and, from other installed packages, the
modules named by the entry points of the group :data:`GROUP` (``rse.algorithms``), e.g. in
the plugin package's ``pyproject.toml``::

    [project.entry-points."rse.algorithms"]
    wmsr = "rse_wmsr.plugin"

A plugin module defines:

* ``ESTIMATOR``: the pydantic model of its ``[estimator]`` table (a
  :class:`scenarios.types.Strict` subclass whose ``algorithm`` field is a one-value
  ``Literal``); the scenario schema's ``[estimator]`` is the union of every plugin's, so a
  plugin adds its section without editing :mod:`scenarios.schema`;
* ``PLANTS``: optional ``{model name: (default params, build(scenario, source) -> PlantModel)}``
  for the named plants it brings (``[plant] model = ...``);
* ``design(exp, *, check) -> object``: the offline design, done once per run
  (``exp.design`` holds it); raise :class:`~estimation.errors.ScenarioError` naming the key;
* ``make_estimator(exp, i)``: a fresh estimator for agent index ``i``;
* ``conditions(exp) -> list[Condition]``: what ``rse check`` prints;
* ``design_json(exp) -> dict``: the design as written to ``design.json``.
* ``graph_conditions(exp) -> list[Condition]``: optional; replaces the generic
  connectivity lines of ``rse check`` (e.g. for an algorithm made for directed graphs).
* ``THREAT_MODEL``: optional :class:`scenarios.helpers.ThreatModel`, what the algorithm
  tolerates (the ``[estimator]`` keys of its sensor and Byzantine-agent budgets, the
  strategies); ``rse redteam`` searches inside it. Without it the algorithm declares no
  sensor or Byzantine budget.

A plugin builds on :mod:`scenarios.helpers` (import it at module level; the schema and the
builder are still being imported when plugins load). An entry point that cannot be loaded,
or whose module breaks this contract, is a :class:`~estimation.errors.PluginError` whose
one-line message names the entry point and its package.
"""

from __future__ import annotations

import importlib
import importlib.metadata
from functools import cache
from types import ModuleType
from typing import Any, Literal, get_args, get_origin

from estimation.errors import PluginError

MODULES = (
    "scenarios.plugins.lee_kim_shim",
    "scenarios.plugins.mitra",
    "scenarios.plugins.mao_tabuada",
    "scenarios.plugins.ugrinovskii",
    "scenarios.plugins.inverters",
)
#: the entry-point group through which other packages add algorithms
GROUP = "rse.algorithms"
#: what every plugin module defines (``PLANTS`` and ``graph_conditions`` are optional)
REQUIRED = ("ESTIMATOR", "design", "make_estimator", "conditions", "design_json")
BUILTIN_PLANTS = ("three_inertia", "lti")
#: built-in modules that bring named plants only (``PLANTS``, no estimator)
PLANT_MODULES = ("scenarios.plugins.grid",)


@cache
def modules() -> tuple[ModuleType, ...]:
    """The built-in plugins, then those of the ``rse.algorithms`` entry points (by name)."""
    mods = [importlib.import_module(m) for m in MODULES]
    algorithms = {algorithm_name(m): m.__name__ for m in mods}
    plants = {name: m.__name__ for m in mods for name in getattr(m, "PLANTS", {})}
    plants.update({name: "the scenario format" for name in BUILTIN_PLANTS})
    plants.update({name: m.__name__ for m in plant_modules() for name in m.PLANTS})
    for ep in entry_points():
        mod = _load(ep)
        _check(mod, origin(ep), algorithms, plants)
        mods.append(mod)
    return tuple(mods)


def entry_points() -> list[importlib.metadata.EntryPoint]:
    """The group's entry points, each once (a package on ``sys.path`` twice is listed twice)."""
    seen: dict[tuple[str, str], importlib.metadata.EntryPoint] = {}
    for ep in importlib.metadata.entry_points(group=GROUP):
        seen.setdefault((ep.name, ep.value), ep)
    return sorted(seen.values(), key=lambda ep: (ep.name, ep.value))


def origin(ep: importlib.metadata.EntryPoint) -> str:
    """``algorithm plugin 'NAME' (= VALUE) of package DIST VERSION``, for messages."""
    dist = getattr(ep, "dist", None)
    pkg = f"package {dist.name} {dist.version}" if dist is not None else "an unknown package"
    return f"algorithm plugin {ep.name!r} (entry point {GROUP}: {ep.name} = {ep.value}) of {pkg}"


def _load(ep: importlib.metadata.EntryPoint) -> Any:
    try:
        return ep.load()
    except Exception as exc:  # whatever the package raises on import, said in one line
        raise PluginError(f"{origin(ep)}: cannot be loaded: {type(exc).__name__}: {exc}") from None


def algorithm_name(mod: Any) -> str:
    """The ``algorithm`` value of a plugin's ``ESTIMATOR`` section."""
    field = mod.ESTIMATOR.model_fields["algorithm"]
    return get_args(field.annotation)[0]


def _check(mod: Any, where: str, algorithms: dict[str, str], plants: dict[str, str]) -> None:
    """The module contract (see the module docstring); records the names it adds."""
    from pydantic import BaseModel

    contract = "(the contract: docs/algorithms/writing-a-plugin.md)"
    missing = [a for a in REQUIRED if not hasattr(mod, a)]
    if missing:
        raise PluginError(f"{where}: does not define {', '.join(missing)} {contract}")
    for a in (*REQUIRED[1:], "graph_conditions"):
        if hasattr(mod, a) and not callable(getattr(mod, a)):
            raise PluginError(f"{where}: {a} must be a function {contract}")
    est = mod.ESTIMATOR
    field = est.model_fields.get("algorithm") if isinstance(est, type) and issubclass(est, BaseModel) else None
    args = get_args(field.annotation) if field is not None else ()
    if field is None or get_origin(field.annotation) is not Literal or len(args) != 1 or not isinstance(args[0], str):
        raise PluginError(f"{where}: ESTIMATOR must be a pydantic model (scenarios.types.Strict) with a field "
                          f"algorithm: Literal['NAME'] {contract}")
    name = args[0]
    if name in algorithms:
        raise PluginError(f"{where}: algorithm {name!r} is already provided by {algorithms[name]}")
    algorithms[name] = where
    _check_threat_model(mod, where, est, contract)
    named = getattr(mod, "PLANTS", {})
    if not isinstance(named, dict):
        raise PluginError(f"{where}: PLANTS must be a dict {{model name: (default params, build)}} {contract}")
    for pname, entry in named.items():
        if not (isinstance(entry, tuple) and len(entry) == 2 and isinstance(entry[0], dict) and callable(entry[1])):
            raise PluginError(f"{where}: PLANTS[{pname!r}] must be (default params, build(scenario, source)) {contract}")
        if pname in plants:
            raise PluginError(f"{where}: plant model {pname!r} is already provided by {plants[pname]}")
        plants[pname] = where


def _check_threat_model(mod: Any, where: str, est: Any, contract: str) -> None:
    from ..common import STRATEGIES, ThreatModel

    tm = getattr(mod, "THREAT_MODEL", None)
    if tm is None:
        return
    if not isinstance(tm, ThreatModel):
        raise PluginError(f"{where}: THREAT_MODEL must be a scenarios.helpers.ThreatModel {contract}")
    for what, key in (("sensors", tm.sensors), ("agents", tm.agents)):
        if key is not None and key not in est.model_fields:
            raise PluginError(f"{where}: THREAT_MODEL.{what} = {key!r} is not a field of its ESTIMATOR {contract}")
    unknown = [s for s in tm.strategies or () if s not in STRATEGIES]
    if unknown:
        raise PluginError(f"{where}: THREAT_MODEL.strategies: unknown strategy {unknown[0]!r}; expected some of "
                          f"{', '.join(STRATEGIES)}")


def threat_model(name: str) -> Any:
    """The :class:`~scenarios.helpers.ThreatModel` of algorithm ``name`` (empty where its plugin declares none)."""
    from ..common import ThreatModel

    return getattr(algorithm(name), "THREAT_MODEL", None) or ThreatModel()


@cache
def plant_modules() -> tuple[ModuleType, ...]:
    """The built-in plant-only modules (:data:`PLANT_MODULES`)."""
    return tuple(importlib.import_module(m) for m in PLANT_MODULES)


def estimator_sections() -> tuple[type, ...]:
    return tuple(m.ESTIMATOR for m in modules())


def plant_model_names() -> tuple[str, ...]:
    return tuple(name for m in (*modules(), *plant_modules()) for name in getattr(m, "PLANTS", {}))


def algorithm(name: str) -> ModuleType:
    """The plugin whose ``ESTIMATOR`` has ``algorithm = name``."""
    for m in modules():
        if algorithm_name(m) == name:
            return m
    raise KeyError(name)


def plant(name: str):
    """``(defaults, build)`` of a plugin's named plant."""
    for m in (*modules(), *plant_modules()):
        if name in getattr(m, "PLANTS", {}):
            return m.PLANTS[name]
    raise KeyError(name)
