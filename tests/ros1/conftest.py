"""Every test here needs rospy: marked ``ros1``, so ``make test`` runs them in .venv-ros1 alone.

ROS 1 (Debian's Python and packages) and ROS 2's wheels cannot share an interpreter: the main
environment runs ``pytest -m "not ros1"``, the ROS 1 one ``pytest -m ros1``.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
IMPORT_ROSPY = ("test_early_pushes.py", "test_param_mirror.py")
"""Modules that import rospy as they load (they skip without it)."""

if importlib.util.find_spec("rospy") is None:
    # Where rospy is missing (the main environment) they are not collected at all: their tests
    # are ros1's, run in the other environment, and a module's skip would say "skipped" for them.
    # Elsewhere here a missing rospy is a skip, and a failure when CI=true (rosnet.require_ros1).
    collect_ignore = list(IMPORT_ROSPY)


@pytest.hookimpl(tryfirst=True)  # before -m selects by marker
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Mark ``ros1`` each test of this directory (the hook sees every test of the session)."""
    for item in items:
        if item.path.is_relative_to(HERE):
            item.add_marker(pytest.mark.ros1)
