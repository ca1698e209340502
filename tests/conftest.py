"""What every test module shares: how an independent check whose tool is missing behaves.

The checks against real third-party tools (Debian's libopenigtlink, chromium, the ``myfbgcommunication`` FiSpec
client, the README session run from a checkout's ``.venv``) are the project's independent oracles. On a
developer's machine without the tool they skip; under CI (``CI`` set to ``true``/``1``, as CI services do and
``.ci/run`` does) a missing tool fails the run, so a skip can never hide a check that did not happen.
"""

from __future__ import annotations

import importlib
import os

import pytest

__all__ = ["IN_CI", "require_module", "require_tool"]

#: whether the tests run under CI, where every independent check must run
IN_CI = os.environ.get("CI", "").strip().lower() in ("1", "true", "yes", "on")


def require_tool(available: bool, what: str) -> None:
    """Call at the start of a test that needs ``what``: nothing if it is available; otherwise fail under CI and
    skip outside it (``what`` says what is missing and how to install it)."""
    if available:
        return
    if IN_CI:
        pytest.fail(f"{what} (CI=true: an independent check must run, not skip)", pytrace=False)
    pytest.skip(what, allow_module_level=True)


def require_module(name: str, what: str):
    """Import ``name`` for a test (module level or inside one), under :func:`require_tool`'s rule."""
    try:
        return importlib.import_module(name)
    except ImportError:
        require_tool(False, f"{name} is not importable: {what}")
