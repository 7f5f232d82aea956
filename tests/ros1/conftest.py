"""Every test here needs rospy: marked ``ros1``, so ``make test`` runs them in .venv-ros1 alone.

ROS 1 (Debian's Python and packages) and ROS 2's wheels cannot share an interpreter: the main
environment runs ``pytest -m "not ros1"``, the ROS 1 one ``pytest -m ros1``.
"""

from __future__ import annotations

from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent


@pytest.hookimpl(tryfirst=True)  # before -m selects by marker
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Mark ``ros1`` each test of this directory (the hook sees every test of the session)."""
    for item in items:
        if item.path.is_relative_to(HERE):
            item.add_marker(pytest.mark.ros1)
