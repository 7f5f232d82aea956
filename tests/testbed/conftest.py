"""Testbed fixtures: skip without privileges locally, fail in CI where they must be present."""

from __future__ import annotations

import pytest

from dbml.testbed import privilege_problem
from tests.conftest import require


@pytest.fixture(scope="session")
def netns_privilege() -> None:
    """Stop a namespace test early when this process cannot build namespaces."""
    require(privilege_problem(), what="be able to build network namespaces")
