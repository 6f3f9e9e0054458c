"""Validation errors as one readable line per problem, in the scenario format's words.

:func:`explain` turns a pydantic ``ValidationError`` into one
:class:`~estimation.errors.ScenarioError` naming the key path, what to write and what was
found. The validator's own vocabulary never reaches the user: the tags pydantic inserts
in the paths of unions are removed, the alternatives of a union are said in one line
(``agents: expected a list or a table, got 5``), a vector where a matrix is expected is
one line that shows the rows (``sensors[0].C is a list of rows: [[1, 0, 0]]``), and a
string where a tagged table is expected shows the table (``network.graph = { kind = "ring" }``).
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from typing import Any

from pydantic import BaseModel, ValidationError
from pydantic_core import ErrorDetails

from estimation.errors import ScenarioError

_DISCRIMINATORS = ("kind", "algorithm", "target")
#: what a value of each pydantic error type should have been, in the format's words
_EXPECTED = {
    "list_type": "a list", "tuple_type": "a list", "dict_type": "a table", "model_type": "a table",
    "model_attributes_type": "a table", "float_type": "a number", "float_parsing": "a number",
    "int_type": "an integer", "int_parsing": "an integer", "int_from_float": "an integer", "string_type": "a string",
    "bool_type": "true or false", "bool_parsing": "true or false", "literal_error": "one of the listed words",
}


def _loc(loc: Iterable[Any]) -> str:
    parts: list[str] = []
    for p in loc:
        if isinstance(p, int):
            parts.append(f"[{p}]")
        else:
            parts.append(("." if parts else "") + str(p))
    return "".join(parts) or "(top level)"


def _is_union_tag(p: str, node: Any) -> bool:
    """A path element pydantic adds for a union member (``CellPatrols``,
    ``list[function-after[...]]``), not a key of the scenario."""
    if not isinstance(node, dict):
        return True
    if p in node:
        return False
    return "[" in p or (p[:1].isupper() and any(c.islower() for c in p))


def _strip_tags(loc: tuple, data: Any) -> list:
    """Remove the discriminator values and union member names pydantic inserts in paths.

    Walks the data along the path: a path element that is not a key of the current table
    but equals its ``kind`` / ``algorithm`` / ``target``, or names a union member, is a tag.
    """
    out: list = []
    node = data
    for p in loc:
        if isinstance(p, str) and (
            (isinstance(node, dict) and p not in node and any(node.get(d) == p for d in _DISCRIMINATORS))
            or _is_union_tag(p, node)
        ):
            continue
        out.append(p)
        node = _child(node, p)
    return out


def _child(node: Any, p: Any) -> Any:
    if isinstance(node, dict):
        return node.get(p)
    if isinstance(node, list) and isinstance(p, int) and 0 <= p < len(node):
        return node[p]
    return None


def _at(data: Any, loc: Iterable[Any]) -> Any:
    node = data
    for p in loc:
        node = _child(node, p)
    return node


def _discriminator(loc: list, model: type[BaseModel]) -> str | None:
    """The discriminator (``kind``, ...) of the tagged union at ``loc`` of ``model``, if any."""
    field = None
    current: Any = model
    for p in loc:
        if isinstance(p, int):
            continue
        if not (isinstance(current, type) and issubclass(current, BaseModel)) or p not in current.model_fields:
            return None
        field = current.model_fields[p]
        current = field.annotation
        args = getattr(current, "__args__", ())
        if args and getattr(current, "__origin__", None) in (list, tuple):
            current = args[0]
    if field is None:
        return None
    return field.discriminator if isinstance(field.discriminator, str) else _nested_discriminator(field.annotation)


def _nested_discriminator(annotation: Any) -> str | None:
    """The discriminator of a tagged union inside ``annotation`` (e.g. ``Init | None``)."""
    for meta in getattr(annotation, "__metadata__", ()):
        disc = getattr(meta, "discriminator", None)
        if isinstance(disc, str):
            return disc
    for arg in getattr(annotation, "__args__", ()):
        disc = _nested_discriminator(arg)
        if disc is not None:
            return disc
    return None


def _message(e: ErrorDetails, found: Any) -> str:
    ctx = e.get("ctx") or {}
    typ = e["type"]
    if typ == "union_tag_invalid":
        disc = str(ctx.get("discriminator", "kind")).strip("'")
        tags = str(ctx.get("expected_tags", "")).replace("'", "")
        msg = f"unknown {disc} {ctx.get('tag')!r}; expected one of {tags}"
        if disc == "algorithm":
            msg += " (an algorithm from another package is found once that package is installed: rse.algorithms entry points)"
        return msg
    if typ == "union_tag_not_found":
        return f"missing key {str(ctx.get('discriminator', '')).strip(chr(39))!r}"
    if typ == "extra_forbidden":
        return "unknown key (not part of the scenario format)"
    if typ == "missing":
        return "missing required key"
    if typ == "literal_error":
        return f"expected one of {ctx.get('expected')}, got {found!r}"
    if typ == "value_error":
        return str(ctx.get("error", e["msg"]))
    if typ == "finite_number":
        return f"expected a finite number, got {found!r}"
    if typ == "int_parsing_size":
        return f"expected an integer of at most 19 digits, got {found!r}"
    return f"{e['msg'][0].lower()}{e['msg'][1:]}, got {found!r}"


def _toml(v: Any) -> str:
    return json.dumps(v, default=str)


def problems(err: ValidationError, data: Any, model: type[BaseModel] | None = None) -> list[str]:
    """One line per problem: ``key.path: message``."""
    entries: list[tuple[list, str, str, Any]] = []
    rows_of: dict[str, Any] = {}
    for e in err.errors(include_url=False):
        loc = _strip_tags(e["loc"], data)
        found = e.get("input")
        typ = e["type"]
        msg = _message(e, found)
        if typ in ("model_attributes_type", "dict_type", "model_type") and isinstance(found, str) and model is not None:
            disc = _discriminator(loc, model)
            if disc is not None:
                msg = f"expected a table, e.g. {_loc(loc)} = {{ {disc} = {_toml(found)} }}, got {found!r}"
        entries.append((loc, typ, msg, found))
    alone = [e for e in entries if e[1] == "list_type" and sum(o[0] == e[0] for o in entries) == 1]
    for loc, _, _, _ in alone:  # a number where a list is expected, and nothing else wrong there
        parent = _at(data, loc[:-1])
        if (loc and isinstance(loc[-1], int) and isinstance(parent, list) and parent
                and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in parent)):
            rows_of[_loc(loc[:-1])] = parent  # a vector where a matrix (list of rows) is expected
    entries = [e for e in entries if not (e in alone and _loc(e[0][:-1]) in rows_of)]
    lines = [f"{key} is a list of rows: [{_toml(row)}]" for key, row in rows_of.items()]
    return lines + _grouped(_applicable(entries), data)


def _applicable(entries: list[tuple[list, str, str, Any]]) -> list[tuple[list, str, str, Any]]:
    """Drop the union alternatives the value does not even have the shape of: a type
    mismatch at a path under which another alternative reports a deeper problem
    (``agents`` is a table, so its "should be a list" is noise beside ``agents.periods[0]``)."""
    def deeper(loc: list) -> bool:
        return any(len(other) > len(loc) and other[: len(loc)] == loc for other, _, _, _ in entries)

    return [e for e in entries if not (e[1] in _EXPECTED and deeper(e[0]))]


def _grouped(entries: list[tuple[list, str, str, Any]], data: Any) -> list[str]:
    """Lines from the entries: the missing keys of one table, the missing items of one
    list and the alternatives of one union each said in one line."""
    by_loc: dict[str, list[tuple[str, str, Any]]] = {}
    missing: dict[str, list] = {}
    for loc, typ, _msg, _found in entries:
        if typ == "missing" and loc:
            missing.setdefault(_loc(loc[:-1]), []).append(loc[-1])
    unknown: dict[str, list] = {}
    for loc, typ, msg, found in entries:
        if typ == "missing" and loc:
            continue
        if typ == "extra_forbidden" and loc and _loc(loc[:-1]) in missing:  # said with the table's missing keys
            unknown.setdefault(_loc(loc[:-1]), []).append(loc[-1])
            continue
        by_loc.setdefault(_loc(loc), []).append((typ, msg, found))
    lines = []
    short = {p for p, names in missing.items() if all(isinstance(n, int) for n in names)}  # lists too short
    for key in [k for k in by_loc if any(k.startswith(p + "[") for p in short)]:
        del by_loc[key]  # its items' own problems: the list's "expected N items" says it
    for parent, names in missing.items():
        if all(isinstance(n, int) for n in names):
            value = _at(data, [p for p in _path_of(parent, entries)])
            lines.append(f"{parent}: expected {max(names) + 1} items, got {_toml(value)}")
        elif len(names) == 1 and parent not in unknown:
            lines.append(f"{_loc([*_path_of(parent, entries), names[0]])}: missing required key")
        elif len(names) > 1 or parent in unknown:
            extra = f"; unknown key(s) {', '.join(repr(n) for n in unknown[parent])}" if parent in unknown else ""
            lines.append(f"{parent}: missing required key(s) {', '.join(repr(n) for n in names)}{extra}")
    for key, msgs in by_loc.items():
        finer = [m for m in msgs if m[0] not in _EXPECTED]
        if finer:  # the value has the shape of an alternative and fails its finer check: that is the problem
            msgs = finer
        if len(msgs) > 1 and all(t in _EXPECTED for t, _, _ in msgs):  # the alternatives of a union, in one line
            kinds = list(dict.fromkeys(_EXPECTED[t] for t, _, _ in msgs))
            lines.append(f"{key}: expected {' or '.join(kinds)}, got {msgs[0][2]!r}")
        else:
            lines.extend(f"{key}: {m}" for m in dict.fromkeys(m for _, m, _ in msgs))
    return lines


def _path_of(parent: str, entries: list[tuple[list, str, str, Any]]) -> list:
    """The path (list) whose text is ``parent``, from the entries' paths."""
    for loc, _, _, _ in entries:
        if loc and _loc(loc[:-1]) == parent:
            return loc[:-1]
    return []


def explain(err: ValidationError, source: str, data: Any, model: type[BaseModel] | None = None) -> ScenarioError:
    """Turn a pydantic error into one readable :class:`ScenarioError` (all problems listed)."""
    lines = problems(err, data, model)
    if len(lines) == 1:
        return ScenarioError(lines[0], source=source)
    return ScenarioError(f"{len(lines)} problems:\n  " + "\n  ".join(lines), source=source)
