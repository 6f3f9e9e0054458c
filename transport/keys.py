"""Key expressions: the one place that builds and parses them.

Every key starts with ``rse/{run}`` so that two teams on one machine never hear each
other. The families::

    rse/{run}/plant/loc/{loc}        a sensing location's measurement   (sender: plant)
    rse/{run}/plant/truth            the true state, for the monitor    (sender: plant)
    rse/{run}/agent/{i}/est          agent i's estimate, broadcast      (sender: i)
    rse/{run}/agent/{i}/est/{j}      agent i's estimate addressed to j  (sender: i, receiver: j)
    rse/{run}/ctl/{what}             control, sender not implied        (sender: any)
    rse/{run}/ctl/{what}/{i}         control from agent i, e.g. ``ctl/done/3``  (sender: i)
    rse/{run}/ctl/{what}/{role}      control from a role, e.g. ``ctl/round/plant``,
                                     role in plant, monitor, launcher   (sender: role id)
    rse/{run}/alive/{role}/{i}       liveliness token of a process      (no payload)

Ids are canonical decimal integers (``3``, never ``03`` or ``+3``), so that one id has
exactly one key and the sender a key implies is unambiguous. Usage::

    keys = Keys("lks-20260101-1a2b")
    session.put(keys.est(3), payload)                 # rse/lks-.../agent/3/est
    session.declare_subscriber(keys.est_pattern(to=5), cb)  # rse/lks-.../agent/*/est/5
    parsed = keys.parse(received_key)                 # ParsedKey(kind="est", ids=(3, 5), ...)
    decode(payload, schema=..., expected_sender=parsed.sender,
           expected_receiver=parsed.receiver)

Building a key from a bad argument raises ``ValueError`` (a programming or configuration
error); parsing a received key that is not one of ours raises
:class:`~estimation.errors.MessageError` with reason ``"key"`` (untrusted input, dropped).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from estimation.errors import MessageError
from transport.codec import LAUNCHER_ID, MAX_ID, MONITOR_ID, PLANT_ID

__all__ = [
    "PREFIX",
    "KEY_LOC",
    "KEY_TRUTH",
    "KEY_EST",
    "KEY_CTL",
    "KEY_ALIVE",
    "ROLES",
    "ROLE_IDS",
    "Keys",
    "ParsedKey",
    "validate_run_id",
    "parse_key",
]

PREFIX = "rse"

KEY_LOC = "loc"
KEY_TRUTH = "truth"
KEY_EST = "est"
KEY_CTL = "ctl"
KEY_ALIVE = "alive"

ROLES = frozenset({"plant", "monitor", "agent", "launcher"})
"""Roles that announce themselves with a liveliness token."""

ROLE_IDS = {"plant": PLANT_ID, "monitor": MONITOR_ID, "launcher": LAUNCHER_ID}
"""The sender ids of the roles that are not agents (how they appear in ``ctl`` keys)."""
_ROLE_NAMES = {v: k for k, v in ROLE_IDS.items()}

MAX_RUN_LEN = 64
_RUN_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}\Z")
_NAME_RE = re.compile(r"[a-z][a-z0-9_]{0,31}\Z")  # ctl {what}
_ID_RE = re.compile(r"(?:0|[1-9][0-9]{0,5})\Z")  # canonical non-negative decimal
_MAX_KEY_LEN = 256


def validate_run_id(run: str) -> str:
    """Return ``run`` if it is a safe run id, else raise ``ValueError``.

    A run id is 1 to 64 characters from ``A-Z a-z 0-9 _ . -``, starting with a letter or
    digit: no ``/`` (key separator), no ``*`` or ``$`` (key-expression wildcards and
    escapes), no ``#`` or ``?`` (selector syntax), no whitespace, nothing non-ASCII.
    """
    if not isinstance(run, str) or not _RUN_RE.match(run):
        raise ValueError(
            f"invalid run id {run!r}: use 1 to {MAX_RUN_LEN} characters from A-Z a-z 0-9 _ . - "
            "starting with a letter or digit (no '/', '*', '$', '#', '?' or whitespace)"
        )
    return run


def _agent_id(i: object, what: str) -> int:
    if type(i) is not int or not 0 <= i <= MAX_ID:
        raise ValueError(f"{what} must be an int in [0, {MAX_ID}], got {i!r}")
    return i


def _name(what: object, label: str) -> str:
    if not isinstance(what, str) or not _NAME_RE.match(what):
        raise ValueError(f"{label} must match [a-z][a-z0-9_]{{0,31}}, got {what!r}")
    return what


@dataclass(frozen=True, slots=True)
class ParsedKey:
    """A received key expression, parsed.

    Attributes
    ----------
    run : str
        The run id.
    kind : str
        ``"loc"``, ``"truth"``, ``"est"``, ``"ctl"`` or ``"alive"``.
    ids : tuple of int
        ``loc``: ``(loc,)``; ``truth``: ``()``; ``est``: ``(i,)`` or ``(i, j)``;
        ``ctl``: ``()`` or ``(sender,)`` (an agent id, or a role id from
        :data:`ROLE_IDS` for ``ctl/{what}/{role}``); ``alive``: ``(i,)``.
    name : str or None
        ``ctl``: the ``{what}``; ``alive``: the role; otherwise ``None``.
    """

    run: str
    kind: str
    ids: tuple[int, ...] = ()
    name: str | None = None

    @property
    def sender(self) -> int | None:
        """The sender id this key implies (for ``decode(expected_sender=...)``).

        The plant (:data:`~transport.codec.PLANT_ID`) for ``loc`` and ``truth``; ``i`` for
        ``agent/{i}/est[/{j}]`` and ``ctl/{what}/{i}``; the role id for
        ``ctl/{what}/{role}``; for ``alive/{role}/{i}`` the agent id ``i`` when the role
        is ``agent``, else the role id; ``None`` for ``ctl/{what}`` (no sender implied).
        """
        kind = self.kind
        if kind == KEY_LOC or kind == KEY_TRUTH:
            return PLANT_ID
        if kind == KEY_EST or (kind == KEY_CTL and self.ids):
            return self.ids[0]
        if kind == KEY_ALIVE:
            return self.ids[0] if self.name == "agent" else ROLE_IDS[self.name]  # type: ignore[index]
        return None

    @property
    def receiver(self) -> int | None:
        """The addressed receiver ``j`` of ``agent/{i}/est/{j}``, else ``None``."""
        return self.ids[1] if self.kind == KEY_EST and len(self.ids) == 2 else None

    @property
    def loc(self) -> int | None:
        """The location of ``plant/loc/{loc}``, else ``None``."""
        return self.ids[0] if self.kind == KEY_LOC else None


class Keys:
    """Builds every key expression of one run (see the module docstring).

    Parameters
    ----------
    run : str
        The run id; validated by :func:`validate_run_id`.
    """

    __slots__ = ("run", "_root", "_parsed")

    #: parsed keys remembered per run (a team uses a few keys per member, over and over)
    CACHE_SIZE = 4096

    def __init__(self, run: str) -> None:
        self.run = validate_run_id(run)
        self._root = f"{PREFIX}/{run}"
        self._parsed: dict[str, ParsedKey] = {}

    def __repr__(self) -> str:
        return f"Keys({self.run!r})"

    # -- concrete keys (for put / declare_publisher / declare_token)

    def plant_loc(self, loc: int) -> str:
        """``rse/{run}/plant/loc/{loc}``: the measurement of sensing location ``loc``."""
        return f"{self._root}/plant/loc/{_agent_id(loc, 'loc')}"

    def plant_truth(self) -> str:
        """``rse/{run}/plant/truth``: the true state (monitor only)."""
        return f"{self._root}/plant/truth"

    def est(self, i: int, to: int | None = None) -> str:
        """``rse/{run}/agent/{i}/est``, or ``.../est/{to}`` when addressed to agent ``to``."""
        base = f"{self._root}/agent/{_agent_id(i, 'agent id')}/est"
        return base if to is None else f"{base}/{_agent_id(to, 'receiver id')}"

    def ctl(self, what: str, sender: int | None = None) -> str:
        """``rse/{run}/ctl/{what}``, or the key that names its sender: ``.../ctl/{what}/{i}``
        for agent ``i``, ``.../ctl/{what}/{role}`` for a role id (``PLANT_ID`` ->
        ``plant``, ``MONITOR_ID`` -> ``monitor``, ``LAUNCHER_ID`` -> ``launcher``).
        """
        base = f"{self._root}/ctl/{_name(what, 'ctl name')}"
        if sender is None:
            return base
        if type(sender) is int and sender in _ROLE_NAMES:
            return f"{base}/{_ROLE_NAMES[sender]}"
        return f"{base}/{_agent_id(sender, 'ctl sender id')}"

    def alive(self, role: str, i: int = 0) -> str:
        """``rse/{run}/alive/{role}/{i}``: the liveliness token of a process."""
        if role not in ROLES:
            raise ValueError(f"role must be one of {sorted(ROLES)}, got {role!r}")
        return f"{self._root}/alive/{role}/{_agent_id(i, 'id')}"

    # -- patterns (for declare_subscriber)

    def plant_loc_pattern(self) -> str:
        """``rse/{run}/plant/loc/*``: every location."""
        return f"{self._root}/plant/loc/*"

    def est_pattern(self, *, sender: int | None = None, to: int | None = None) -> str:
        """Estimates: broadcast ones (``to=None``) or those addressed to ``to``,
        from every agent (``sender=None``) or from ``sender``.
        """
        who = "*" if sender is None else str(_agent_id(sender, "sender id"))
        base = f"{self._root}/agent/{who}/est"
        return base if to is None else f"{base}/{_agent_id(to, 'receiver id')}"

    def ctl_pattern(self, what: str | None = None) -> str:
        """``rse/{run}/ctl/**`` or ``rse/{run}/ctl/{what}/**`` (``**`` also matches nothing)."""
        return f"{self._root}/ctl/**" if what is None else f"{self._root}/ctl/{_name(what, 'ctl name')}/**"

    def alive_pattern(self, role: str | None = None) -> str:
        """``rse/{run}/alive/**`` or ``rse/{run}/alive/{role}/*``."""
        if role is None:
            return f"{self._root}/alive/**"
        if role not in ROLES:
            raise ValueError(f"role must be one of {sorted(ROLES)}, got {role!r}")
        return f"{self._root}/alive/{role}/*"

    def all_pattern(self) -> str:
        """``rse/{run}/**``: everything of this run."""
        return f"{self._root}/**"

    # -- parsing

    def parse(self, key: str) -> ParsedKey:
        """Parse a received key of this run (a key of another run is rejected).

        Valid keys are remembered (at most :attr:`CACHE_SIZE`, then the cache starts
        afresh): :class:`ParsedKey` is immutable and a key always parses the same way."""
        parsed = self._parsed.get(key)
        if parsed is not None:
            return parsed
        parsed = parse_key(key)
        if parsed.run != self.run:
            raise MessageError(f"key {key!r:.120} belongs to run {parsed.run!r}, not {self.run!r}", reason="key")
        if len(self._parsed) >= self.CACHE_SIZE:
            self._parsed.clear()
        self._parsed[key] = parsed
        return parsed


def _bad(key: object, why: str) -> MessageError:
    return MessageError(f"not a valid rse key ({why}): {key!r:.120}", reason="key")


def _parse_id(key: str, chunk: str, what: str) -> int:
    if not _ID_RE.match(chunk):
        raise _bad(key, f"{what} {chunk!r:.20} is not a canonical non-negative integer")
    value = int(chunk)
    if value > MAX_ID:
        raise _bad(key, f"{what} {value} is above {MAX_ID}")
    return value


def parse_key(key: str) -> ParsedKey:
    """Parse a received key expression into a :class:`ParsedKey`.

    Raises :class:`~estimation.errors.MessageError` (reason ``"key"``) for anything that
    is not exactly one of the families in the module docstring.
    """
    if not isinstance(key, str):
        raise _bad(key, f"a key is a str, got {type(key).__name__}")
    if len(key) > _MAX_KEY_LEN:
        raise _bad(key, f"longer than {_MAX_KEY_LEN} characters")
    parts = key.split("/")
    if len(parts) < 4 or parts[0] != PREFIX:
        raise _bad(key, f"expected '{PREFIX}/{{run}}/...'")
    run = parts[1]
    if not _RUN_RE.match(run):
        raise _bad(key, "invalid run id")
    family, rest = parts[2], parts[3:]
    n = len(rest)

    if family == "plant":
        if rest == ["truth"]:
            return ParsedKey(run, KEY_TRUTH)
        if n == 2 and rest[0] == "loc":
            return ParsedKey(run, KEY_LOC, (_parse_id(key, rest[1], "location"),))
        raise _bad(key, "expected plant/loc/{loc} or plant/truth")
    if family == "agent":
        if n in (2, 3) and rest[1] == "est":
            i = _parse_id(key, rest[0], "agent id")
            if n == 2:
                return ParsedKey(run, KEY_EST, (i,))
            return ParsedKey(run, KEY_EST, (i, _parse_id(key, rest[2], "receiver id")))
        raise _bad(key, "expected agent/{i}/est or agent/{i}/est/{j}")
    if family == "ctl":
        if n in (1, 2) and _NAME_RE.match(rest[0]):
            if n == 1:
                return ParsedKey(run, KEY_CTL, (), rest[0])
            who = rest[1]
            sender = ROLE_IDS[who] if who in ROLE_IDS else _parse_id(key, who, "ctl sender id")
            return ParsedKey(run, KEY_CTL, (sender,), rest[0])
        raise _bad(key, "expected ctl/{what}, ctl/{what}/{i} or ctl/{what}/{role}")
    if family == "alive":
        if n == 2 and rest[0] in ROLES:
            return ParsedKey(run, KEY_ALIVE, (_parse_id(key, rest[1], "id"),), rest[0])
        raise _bad(key, f"expected alive/{{role}}/{{i}} with role in {sorted(ROLES)}")
    raise _bad(key, f"unknown family {family!r:.20}")

