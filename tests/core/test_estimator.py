"""The estimator's names where users imported them before it became ``dbml.estimator``."""

from __future__ import annotations

import dbml.estimator
from dbml.core import estimator as old_home
from dbml.protocol import messages


def test_the_old_names_are_the_packages_own() -> None:
    for name in old_home.__all__:
        new_home = messages if name == "EstimatorState" else dbml.estimator
        assert getattr(old_home, name) is getattr(new_home, name), name
    assert set(old_home.__all__) == {
        "MAX_SAMPLES",
        "MAX_STREAMS",
        "Arrival",
        "BandwidthEstimator",
        "Design",
        "Estimate",
        "EstimatorSettings",
        "EstimatorState",
        "Phase",
    }
