"""Test tools for backend and plugin authors: shapes, shared physics cases, the parity suite.

Import what you need from the submodules; ``check_backend`` and ``BackendConformance`` are the
one-line entry points (they import pytest only when used).
"""

from __future__ import annotations


def __getattr__(name: str):
    if name in ("check_backend", "BackendConformance"):
        from mosiv_framework.testing import conformance

        return getattr(conformance, name)
    if name in ("run_parity", "ParityReport", "TOLERANCES"):
        from mosiv_framework.testing import parity

        return getattr(parity, name)
    raise AttributeError(f"module 'mosiv_framework.testing' has no attribute {name!r}")


__all__ = ["TOLERANCES", "BackendConformance", "ParityReport", "check_backend", "run_parity"]
