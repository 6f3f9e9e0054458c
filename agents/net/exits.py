"""How a command or a process of the runtime ends: its exit status and its one-line message.

One place for the statuses every command (``rse ...``) and every process of a team exits
with, and for the mapping from the exceptions of :mod:`estimation.errors` to them; the CLI,
the team launcher, the role processes and the API use it. (The maths layer only defines the
exceptions; what a process does with them is decided here.)
"""

from __future__ import annotations

from estimation.errors import ExpectationFailed, RSEError, ScenarioError

EXIT_OK = 0  #: success
EXIT_FAILED = 1  #: a condition (``rse check``) or a process / the run failed
EXIT_BAD_INPUT = 2  #: bad input: usage, a scenario file, an override, a missing file
EXIT_EXPECTATION = 3  #: the run finished but an ``[[expect]]`` bound failed
EXIT_INTERRUPTED = 130  #: Ctrl-C / SIGTERM


def exit_status(exc: BaseException) -> int:
    """The exit status for an exception that ends a command or a process.

    :class:`ScenarioError` -> 2, :class:`ExpectationFailed` -> 3, any other
    :class:`RSEError` or an :class:`OSError` -> 1, an interrupt -> 130; anything else is a
    bug (1, reported as an internal error by the caller).
    """
    if isinstance(exc, ScenarioError):
        return EXIT_BAD_INPUT
    if isinstance(exc, ExpectationFailed):
        return EXIT_EXPECTATION
    if isinstance(exc, KeyboardInterrupt):
        return EXIT_INTERRUPTED
    return EXIT_FAILED


def describe(exc: BaseException) -> str:
    """The one-line message for ``exc`` (an internal error names its type and how to see the
    traceback)."""
    if isinstance(exc, RSEError):
        return str(exc)
    if isinstance(exc, KeyboardInterrupt):
        return "interrupted"
    if isinstance(exc, OSError):
        return f"{exc.strerror or exc}: {exc.filename}" if getattr(exc, "filename", None) else str(exc)
    return f"internal error: {type(exc).__name__}: {exc} (set RSE_DEBUG=1 for the traceback)"
