"""Bad input never hangs or crashes: every scenario file under ``scenarios/``, mutated at
random (a key dropped, a wrong type, zero, negative, huge, NaN or infinite numbers, empty
lists, unknown keys and kinds), directly and as ``--set`` values, is loaded, checked,
built and simulated for a few rounds through the public API under a time limit. Each
example either runs or raises a :class:`ScenarioError` whose message is one line that
starts with the key path it is about: never another exception, never a hang.

In CI a fixed number of derandomized examples (tests/conftest.py's profiles);
``HYPOTHESIS_PROFILE=explore`` draws :data:`EXPLORE_EXAMPLES` new ones (or
``RSE_FUZZ_EXAMPLES``).
"""

from __future__ import annotations

import copy
import math
import os
import re
import signal
import tomllib
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import rse
from estimation.errors import ScenarioError
from scenarios.loader import toml_value
from tests.conftest import scenario_params

ROOT = Path(__file__).resolve().parents[2]


#: every scenario file; those whose algorithm or plant needs an optional extra (cvxpy,
#: pandapower) skip without it (tests/conftest.py's marks)
FILES = sorted((ROOT / "scenarios").glob("*.toml"))
RAW = {p.name: tomllib.loads(p.read_text()) for p in FILES}
CI_EXAMPLES = 84  # 6 per scenario file
EXPLORE_EXAMPLES = 2000
EXAMPLES = int(os.environ.get("RSE_FUZZ_EXAMPLES",
                              EXPLORE_EXAMPLES if os.environ.get("HYPOTHESIS_PROFILE") == "explore" else CI_EXAMPLES))
#: seconds one example may take (load, check, build, a few rounds) before it counts as a hang
TIME_LIMIT = 60
SIM_ROUNDS = 3
SECTIONS = ("run", "plant", "sensors", "agents", "network", "estimator", "attacks", "output", "expect", "redteam")
#: a message starts with the key path it is about (``run.dt:``, ``sensors[0].C is ...``,
#: ``agents.per_cell x cells:``, ``(top level):``)
KEY_FIRST = re.compile(r"^(\(top level\)|(" + "|".join(SECTIONS) + r")\b[\w.\[\]]*)( is |:| x | / | \()")

MUTATIONS: list[Any] = [
    "drop", "unknown_key", 0, -1, -0.5, 1e300, -1e300, 10**30, math.nan, math.inf, -math.inf, [], {}, "x", True,
    [[1.0]], "nope-kind",
]


def _paths(node: Any, prefix: tuple = ()) -> list[tuple]:
    """Every key path of a scenario mapping (tables, values, list items)."""
    out = [prefix] if prefix else []
    if isinstance(node, dict):
        for k, v in node.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(node, list) and len(node) <= 8:
        for i, v in enumerate(node):
            out += _paths(v, (*prefix, i))
    return out


PATHS = {name: _paths(raw) for name, raw in RAW.items()}


class Hang(Exception):
    pass


def _alarm(signum, frame):
    raise Hang(f"an example took more than {TIME_LIMIT} s")


def _mutate(data: dict, path: tuple, mutation: Any) -> dict:
    d = copy.deepcopy(data)
    node: Any = d
    for p in path[:-1]:
        node = node[p]
    last = path[-1]
    if mutation == "drop":
        if isinstance(node, list):
            node.pop(last)
        else:
            del node[last]
    elif mutation == "unknown_key":
        target = node[last]
        if isinstance(target, dict):
            target["bogus_key"] = 1
        else:
            node[last] = {"bogus_key": 1}
    elif mutation == "nope-kind":
        target = node[last]
        if isinstance(target, dict) and any(k in target for k in ("kind", "algorithm", "target")):
            tag = next(k for k in ("kind", "algorithm", "target") if k in target)
            target[tag] = "nope"
        else:
            node[last] = "nope"
    else:
        node[last] = mutation
    return d


def _override(path: tuple, mutation: Any) -> str:
    key = ".".join(str(p) for p in path)
    if mutation in ("drop", "unknown_key", "nope-kind"):
        return f"{key}.bogus_key=1" if mutation == "unknown_key" else f"{key}=nope"
    if isinstance(mutation, float) and not math.isfinite(mutation):
        text = "nan" if math.isnan(mutation) else ("inf" if mutation > 0 else "-inf")
        return f"{key}={text}"
    return f"{key}={toml_value(mutation)}"


def _few_rounds(frozen: dict) -> dict:
    d = copy.deepcopy(frozen)
    d["run"].pop("duration", None)
    d["run"]["rounds"] = SIM_ROUNDS
    return d


def _exercise(data: dict, source: str, overrides: list[str]) -> None:
    """Load, check, build and simulate a few rounds; a ScenarioError must be one line
    starting with a key path."""
    try:
        exp = rse.load(data, source=source, set=overrides, check_conditions=False)  # the size budget: full horizon
        rse.check(exp)
        small = rse.load(_few_rounds(exp.frozen), source=source)  # a run's own checks (design, graph)
        rse.simulate(small)
    except ScenarioError as exc:
        detail = exc.detail
        assert "\n" not in str(exc), f"not one line: {exc}"
        assert KEY_FIRST.match(detail), f"does not start with a key path: {exc}"


def _run_with_limit(data: dict, source: str, overrides: list[str]) -> None:
    old = signal.signal(signal.SIGALRM, _alarm)
    signal.alarm(TIME_LIMIT)
    try:
        _exercise(data, source, overrides)
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def mutations(name: str):
    """(key path, mutation, as a --set value?) for the scenario file ``name``."""
    return st.tuples(st.sampled_from(PATHS[name]), st.sampled_from(MUTATIONS), st.booleans())


#: examples per scenario file (every file is fuzzed; EXAMPLES in all)
PER_FILE = max(1, EXAMPLES // max(1, len(FILES)))
FUZZ = settings(max_examples=PER_FILE, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@pytest.mark.parametrize("scenario", scenario_params(FILES))
@FUZZ
@given(data=st.data())
def test_mutated_scenarios_run_or_name_the_key(scenario, data):
    name = scenario.name
    path, mutation, as_override = data.draw(mutations(name))
    raw = RAW[name]
    if as_override and mutation != "drop":
        _run_with_limit(raw, name, [_override(path, mutation)])
    else:
        _run_with_limit(_mutate(raw, path, mutation), name, [])


def test_key_first_pattern_is_strict():
    """The assertion the fuzz test makes is not vacuous: messages that do not lead with a
    key path (validator jargon, a Python exception's text) fail it."""
    assert KEY_FIRST.match("run.dt: expected a finite number, got inf")
    assert KEY_FIRST.match("sensors[0].C is a list of rows: [[1, 0, 0]]")
    assert KEY_FIRST.match("agents.per_cell x cells: 4,000,000 agents exceed the limit")
    assert not KEY_FIRST.match("cannot convert float NaN to integer")
    assert not KEY_FIRST.match("list[function-after[_one(), AgentSpec]]: input should be a valid list")
