"""Testbed fixtures: skip without privileges locally, fail in CI where they must be present."""

from __future__ import annotations

import os

import pytest

from dbml.testbed import privilege_problem


@pytest.fixture(scope="session")
def netns_privilege() -> None:
    """Stop a namespace test early when this process cannot build namespaces."""
    problem = privilege_problem()
    if problem is None:
        return
    if os.environ.get("CI") == "true":
        pytest.fail(f"CI must be able to build network namespaces: {problem}")
    pytest.skip(problem)
