"""Estimate a shared link's usable capacity from what the receivers get (pure: no I/O, no clock).

The paper assumes the budget is known; real radio links are not. ``BandwidthEstimator`` keeps
what every design shares (streams, silences, outages, the update loop, the bounds, the floor and
the cap, :mod:`~dbml.estimator.shared`); a design is a detector of its own with its own settings
(:mod:`~dbml.estimator.queue`, the default; :mod:`~dbml.estimator.trendline`;
:mod:`~dbml.estimator.delivery_rate`), named in :mod:`~dbml.estimator.designs`. What the
estimator tells others travels as ``dbml.protocol.messages.EstimatorState``.
"""

from dbml.estimator.base import Arrival, Decision, Detector, DetectorSettings, Estimate, Phase, View
from dbml.estimator.delivery_rate import DeliveryRateSettings
from dbml.estimator.designs import DESIGNS, Design, design_of, settings_of
from dbml.estimator.queue import QueueSettings
from dbml.estimator.shared import MAX_SAMPLES, MAX_STREAMS, BandwidthEstimator, EstimatorSettings
from dbml.estimator.trendline import TrendlineSettings

__all__ = [
    "DESIGNS",
    "MAX_SAMPLES",
    "MAX_STREAMS",
    "Arrival",
    "BandwidthEstimator",
    "Decision",
    "DeliveryRateSettings",
    "Design",
    "Detector",
    "DetectorSettings",
    "Estimate",
    "EstimatorSettings",
    "Phase",
    "QueueSettings",
    "TrendlineSettings",
    "View",
    "design_of",
    "settings_of",
]
