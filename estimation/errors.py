"""The exceptions of the runtime, in one place.

Every layer raises these, so a caller can catch by kind. The tree::

    RSEError (Exception)                     base of everything raised on purpose
    +-- ScenarioError (RSEError, ValueError)     a scenario file or override is wrong;
    |                                            the message names file, key path,
    |                                            what was expected and what was found
    +-- DesignError (RSEError, ValueError)       an offline design step cannot succeed
    |   |                                        for these matrices (no common basis,
    |   |                                        unobservable sensor set, no MEDAG,
    |   |                                        infeasible LMI, ...)
    |   +-- InfeasibleError (DesignError)        an LMI / convex programme is infeasible
    +-- NumericalError (RSEError, ArithmeticError) an online computation left its domain
    |                                            (a Riccati solution stopped being
    |                                            positive definite, overflow, ...)
    +-- MessageError (RSEError, ValueError)      bytes from the network that do not decode
    |                                            to a valid message (dropped and counted)
    +-- TransportError (RSEError, RuntimeError)  a session, bus or peer cannot be reached
    +-- ExpectationFailed (RSEError)             a run finished but an ``[expect]`` bound
    |                                            of the scenario does not hold
    +-- PluginError (RSEError)                   an algorithm plugin from another package
                                                 cannot be loaded or breaks the module
                                                 contract (the message names the package)

``estimation`` owns this module because every other layer may import from
``estimation`` and ``estimation`` imports from none of them. The exit statuses a command
or a process maps these to live with the processes, in :mod:`agents.net.exits`.
"""

from __future__ import annotations


class RSEError(Exception):
    """Base class of the runtime's own exceptions."""


class ScenarioError(RSEError, ValueError):
    """A scenario file, or a ``--set`` override, is invalid.

    Parameters
    ----------
    message : str
        What is wrong, already naming the key path, the expectation and what was found.
    source : str, optional
        The file (or ``--set``) the error comes from; prefixed to the message.
    """

    def __init__(self, message: str, *, source: str | None = None) -> None:
        self.source = source
        self.detail = message
        super().__init__(f"{source}: {message}" if source else message)


class DesignError(RSEError, ValueError):
    """An offline design step (decomposition, gains, graph condition) cannot succeed."""


class InfeasibleError(DesignError):
    """A convex programme (LMI) is infeasible or the solver failed to certify it."""


class NumericalError(RSEError, ArithmeticError):
    """An online numerical computation left its domain of validity."""


class MessageError(RSEError, ValueError):
    """Untrusted bytes did not decode to a valid message.

    ``reason`` is a short machine-friendly tag (``"size"``, ``"decode"``, ``"keys"``,
    ``"type"``, ``"nonfinite"``, ``"shape"``, ``"sender"``, ``"version"``) used for the
    per-sender rejection counters.
    """

    def __init__(self, message: str, *, reason: str = "invalid") -> None:
        self.reason = reason
        super().__init__(message)


class TransportError(RSEError, RuntimeError):
    """A session, a bus or a peer could not be opened or reached."""


class ExpectationFailed(RSEError):
    """A run completed but at least one ``[expect]`` bound of its scenario failed."""


class PluginError(RSEError):
    """An algorithm plugin (an ``rse.algorithms`` entry point) cannot be loaded or does not
    satisfy the module contract of :mod:`scenarios.plugins`."""
