"""The designs by name: how overuse is read and what a cut and an increase are.

``queue`` (the default, the only one the product runs), ``trendline`` (after WebRTC GCC) and
``delivery-rate`` (after BBR); docs/estimator.md compares them on recorded traces. A design is
picked by its settings: ``EstimatorSettings(detector=settings_of(Design.TRENDLINE))``.
"""

from __future__ import annotations

import enum
from collections.abc import Callable, Mapping
from typing import Any

from dbml.core.errors import SpecError
from dbml.core.spec import short_repr
from dbml.estimator.base import DetectorSettings
from dbml.estimator.delivery_rate import DeliveryRateSettings
from dbml.estimator.queue import QueueSettings
from dbml.estimator.shared import EstimatorSettings
from dbml.estimator.trendline import TrendlineSettings

__all__ = ["DEFAULT_DESIGN", "DESIGNS", "Design", "design_of", "settings_of"]


class Design(enum.StrEnum):
    """A design's name (``--design`` in bench/estimator_replay.py)."""

    QUEUE = "queue"
    TRENDLINE = "trendline"
    DELIVERY_RATE = "delivery-rate"


DESIGNS: Mapping[Design, Callable[..., DetectorSettings]] = {
    Design.QUEUE: QueueSettings,
    Design.TRENDLINE: TrendlineSettings,
    Design.DELIVERY_RATE: DeliveryRateSettings,
}
"""Each design's settings class: called with keywords, its settings."""


def settings_of(design: Design, **overrides: Any) -> DetectorSettings:
    """``design``'s settings: its defaults, with ``overrides`` (its own fields' names)."""
    return DESIGNS[Design(design)](**overrides)


def design_of(settings: DetectorSettings) -> Design:
    """The design ``settings`` belong to; ``SpecError`` naming them if none."""
    for design, kind in DESIGNS.items():
        if type(settings) is kind:
            return design
    raise SpecError(f"estimator detector={short_repr(settings)} is not one of {', '.join(Design)}")


DEFAULT_DESIGN = design_of(EstimatorSettings().detector)
"""What ``--estimate`` runs unless told otherwise: ``EstimatorSettings``' default detector."""
