"""Helpers of the deployment tests (from :mod:`tests.procs`; the ``procs`` fixture is in tests/conftest.py)."""

from __future__ import annotations

from tests.procs import Procs, child_env, rse_cmd

__all__ = ["Procs", "child_env", "rse_cmd"]
