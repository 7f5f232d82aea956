"""The estimator's names where they were before it became a package of its own.

The estimator is :mod:`dbml.estimator` (what every design shares, and a module per design) and
its state's wire message is :class:`dbml.protocol.messages.EstimatorState`; this module keeps
``from dbml.core.estimator import ...`` working. A design and its thresholds are now chosen
with ``EstimatorSettings(detector=...)`` (``dbml.estimator.designs``).
"""

from dbml.estimator import (
    MAX_SAMPLES,
    MAX_STREAMS,
    Arrival,
    BandwidthEstimator,
    Design,
    Estimate,
    EstimatorSettings,
    Phase,
)
from dbml.protocol.messages import EstimatorState

__all__ = [
    "MAX_SAMPLES",
    "MAX_STREAMS",
    "Arrival",
    "BandwidthEstimator",
    "Design",
    "Estimate",
    "EstimatorSettings",
    "EstimatorState",
    "Phase",
]
