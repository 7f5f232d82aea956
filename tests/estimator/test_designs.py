"""The designs by name, and a design chosen by its settings."""

from __future__ import annotations

import pytest

from dbml.core.errors import SpecError
from dbml.estimator import (
    DESIGNS,
    BandwidthEstimator,
    DeliveryRateSettings,
    Design,
    EstimatorSettings,
    QueueSettings,
    TrendlineSettings,
    design_of,
    settings_of,
)
from dbml.estimator.delivery_rate import DeliveryRateDetector
from dbml.estimator.queue import QueueDetector
from dbml.estimator.trendline import TrendlineDetector

DETECTORS = {
    Design.QUEUE: (QueueSettings, QueueDetector),
    Design.TRENDLINE: (TrendlineSettings, TrendlineDetector),
    Design.DELIVERY_RATE: (DeliveryRateSettings, DeliveryRateDetector),
}


def test_every_design_has_its_settings_and_its_detector() -> None:
    assert set(DESIGNS) == set(Design) == set(DETECTORS)
    assert [d.value for d in Design] == ["queue", "trendline", "delivery-rate"]
    for design, (kind, detector) in DETECTORS.items():
        made = settings_of(design)
        assert type(made) is kind
        assert design_of(made) is design
        estimator = BandwidthEstimator(max_mbit=1.0, settings=EstimatorSettings(detector=made))
        assert type(estimator._detector) is detector


def test_the_default_is_the_queue_design() -> None:
    assert design_of(EstimatorSettings().detector) is Design.QUEUE
    assert type(BandwidthEstimator(max_mbit=1.0)._detector) is QueueDetector


def test_a_design_takes_its_own_fields_only() -> None:
    assert settings_of(Design.TRENDLINE, frames=10) == TrendlineSettings(frames=10)
    assert settings_of(Design("delivery-rate"), probe_gain=1.2).probe_gain == 1.2  # type: ignore[attr-defined]
    with pytest.raises(TypeError, match="probe_gain"):
        settings_of(Design.QUEUE, probe_gain=1.2)


def test_what_is_no_design_is_named() -> None:
    with pytest.raises(SpecError, match=r"estimator detector='queue' is not a design's settings"):
        EstimatorSettings(detector="queue")  # type: ignore[arg-type]
    with pytest.raises(SpecError, match="is not one of queue, trendline, delivery-rate"):
        design_of(object())  # type: ignore[arg-type]
