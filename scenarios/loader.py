"""Load a scenario file, apply ``--set`` overrides, validate, and explain errors.

Every error is a :class:`~estimation.errors.ScenarioError` whose message names the file
(or the ``--set`` argument), the key path, what was expected and what was found, e.g.
``scenarios/x.toml: network.graph: unknown kind 'rnig'; expected one of ring, complete, edges``.
"""

from __future__ import annotations

import copy
import json
import tomllib
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from estimation.errors import ScenarioError

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


def _loc(loc: Iterable[Any]) -> str:
    parts: list[str] = []
    for p in loc:
        if isinstance(p, int):
            parts.append(f"[{p}]")
        else:
            parts.append(("." if parts else "") + str(p))
    return "".join(parts) or "(top level)"


def explain(err: ValidationError, source: str, data: Any) -> ScenarioError:
    """Turn a pydantic error into one readable :class:`ScenarioError` (all problems listed)."""
    lines = []
    for e in err.errors(include_url=False):
        ctx = e.get("ctx") or {}
        typ = e["type"]
        found = e.get("input")
        if typ == "union_tag_invalid":
            tags = ctx.get("expected_tags", "").replace("'", "")
            msg = f"unknown {ctx.get('discriminator', 'kind').strip(chr(39))} {ctx.get('tag')!r}; expected one of {tags}"
            if ctx.get("discriminator", "").strip(chr(39)) == "algorithm":
                msg += " (an algorithm from another package is found once that package is installed: rse.algorithms entry points)"
        elif typ == "union_tag_not_found":
            msg = f"missing key {ctx.get('discriminator', '').strip(chr(39))!r}"
        elif typ == "extra_forbidden":
            msg = "unknown key (not part of the scenario format)"
        elif typ == "missing":
            msg = "missing required key"
        elif typ == "literal_error":
            msg = f"expected one of {ctx.get('expected')}, got {found!r}"
        elif typ == "value_error":
            msg = str(ctx.get("error", e["msg"]))
        else:
            msg = f"{e['msg'][0].lower()}{e['msg'][1:]}, got {found!r}"
        loc = _strip_tags(e["loc"], data)
        lines.append(f"{_loc(loc)}: {msg}")
    if len(lines) == 1:
        return ScenarioError(lines[0], source=source)
    return ScenarioError(f"{len(lines)} problems:\n  " + "\n  ".join(lines), source=source)


_DISCRIMINATORS = ("kind", "algorithm", "target")


def _strip_tags(loc: tuple, data: Any) -> list:
    """Remove the discriminator values pydantic inserts in tagged-union paths.

    Walks the data along the path: a path element that is not a key of the current table
    but equals its ``kind`` / ``algorithm`` / ``target`` is such a tag.
    """
    out: list = []
    node = data
    for p in loc:
        if isinstance(node, dict) and isinstance(p, str) and p not in node and any(node.get(d) == p for d in _DISCRIMINATORS):
            continue
        out.append(p)
        if isinstance(node, dict):
            node = node.get(p)
        elif isinstance(node, list) and isinstance(p, int) and 0 <= p < len(node):
            node = node[p]
        else:
            node = None
    return out


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
        raise explain(err, src, data) from None
    return sc, data


def nominal_horizon(raw: dict) -> float | None:
    """The horizon in seconds (``rounds * dt`` or ``duration``) of a scenario mapping
    before overrides; None when its ``[run]`` table is not complete without them."""
    try:
        run = RunSection.model_validate(raw.get("run"))
    except ValidationError:
        return None
    return run.n_rounds * run.dt
