"""Load a scenario file, apply ``--set`` overrides, validate, and explain errors.

Every error is a :class:`~estimation.errors.ScenarioError` whose message names the file
(or the ``--set`` argument), the key path, what was expected and what was found, e.g.
``scenarios/x.toml: network.graph: unknown kind 'rnig'; expected one of ring, complete, edges``.
"""

from __future__ import annotations

import copy
import json
import math
import tomllib
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from estimation.errors import ScenarioError

from .messages import explain
from .schema import RunSection, Scenario


def parse_value(text: str) -> Any:
    """Parse an override value as a TOML value (``5``, ``1e-3``, ``[]``, ``"ring"``, ``{kind="ring"}``).

    Bare words that are not TOML values are taken as strings (``ring`` -> ``"ring"``).
    """
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def toml_value(v: Any) -> str:
    """A Python value as the TOML text :func:`parse_value` reads back (``--set KEY=VALUE``)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple, dict)):
        return json.dumps(v, default=float)
    if isinstance(v, int) or (hasattr(v, "dtype") and getattr(v.dtype, "kind", "") in "iu"):
        return str(int(v))
    return repr(float(v))


def apply_override(data: dict, assignment: str) -> None:
    """Apply one ``key.path=value`` override to the raw scenario mapping in place.

    List elements are addressed by a 0-based index (``attacks.0.value=1.0``).
    """
    source = f"--set {assignment}"
    if "=" not in assignment:
        raise ScenarioError("expected KEY.PATH=VALUE", source=source)
    path, text = assignment.split("=", 1)
    keys = [k.strip() for k in path.strip().split(".")]
    if not path.strip() or any(not k for k in keys):
        raise ScenarioError(f"bad key path {path!r}", source=source)
    value = parse_value(text.strip())
    _check_finite(value, path.strip(), source)
    node: Any = data
    for depth, key in enumerate(keys[:-1]):
        where = ".".join(keys[: depth + 1])
        if isinstance(node, list):
            node = _list_item(node, key, where, source)
        elif isinstance(node, dict):
            if key not in node:
                node[key] = {}
            node = node[key]
        else:
            raise ScenarioError(f"{where}: is a value, not a table; cannot set {path}", source=source)
    last = keys[-1]
    if isinstance(node, list):
        idx = _index(node, last, path, source)
        node[idx] = value
    elif isinstance(node, dict):
        node[last] = value
    else:
        raise ScenarioError(f"{'.'.join(keys[:-1])}: is a value, not a table; cannot set {path}", source=source)


def _check_finite(value: Any, where: str, source: str) -> None:
    """Refuse NaN and infinity anywhere in an override's value (a list, a table)."""
    if isinstance(value, float) and not math.isfinite(value):
        raise ScenarioError(f"{where}: expected a finite number, got {value!r}", source=source)
    if isinstance(value, list):
        for k, v in enumerate(value):
            _check_finite(v, f"{where}[{k}]", source)
    elif isinstance(value, dict):
        for k, v in value.items():
            _check_finite(v, f"{where}.{k}", source)


def _index(node: list, key: str, where: str, source: str) -> int:
    try:
        idx = int(key)
    except ValueError:
        raise ScenarioError(f"{where}: expected a list index, got {key!r}", source=source) from None
    if not -len(node) <= idx < len(node):
        raise ScenarioError(f"{where}: index {idx} out of range (list has {len(node)} items)", source=source)
    return idx


def _list_item(node: list, key: str, where: str, source: str) -> Any:
    return node[_index(node, key, where, source)]


def read_toml(path: str | Path) -> dict:
    """Read a TOML file; errors name the file and the TOML problem."""
    p = Path(path)
    if not p.exists():
        raise ScenarioError("no such file", source=str(path))
    if p.is_dir():
        raise ScenarioError("is a directory, expected a .toml scenario file", source=str(path))
    try:
        with p.open("rb") as fh:
            return tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"TOML syntax error: {exc}", source=str(path)) from None
    except UnicodeDecodeError as exc:
        raise ScenarioError(f"not UTF-8 text: {exc}", source=str(path)) from None


def load(path: str | Path, overrides: Iterable[str] = ()) -> tuple[Scenario, dict]:
    """Read, override and validate a scenario.

    Returns
    -------
    (Scenario, dict)
        The validated model and the raw mapping after overrides (frozen into the manifest).
    """
    raw = read_toml(path)
    return validate(raw, source=str(path), overrides=overrides)


def validate(raw: dict, *, source: str, overrides: Iterable[str] = ()) -> tuple[Scenario, dict]:
    data = copy.deepcopy(raw)
    overrides = list(overrides)
    for ov in overrides:
        apply_override(data, ov)
    try:
        sc = Scenario.model_validate(data)
    except ValidationError as err:
        src = source + (f" (with --set {' '.join(overrides)})" if overrides else "")
        raise explain(err, src, data, Scenario) from None
    return sc, data


def nominal_horizon(raw: dict) -> float | None:
    """The horizon in seconds (``rounds * dt`` or ``duration``) of a scenario mapping
    before overrides; None when its ``[run]`` table is not complete without them."""
    try:
        run = RunSection.model_validate(raw.get("run"))
    except ValidationError:
        return None
    return run.n_rounds * run.dt
