"""Priorities: from environment events to a raw priority, and the size-weighted normalisation.

The raw priority of a channel is a number in [0, 1] computed from events (paper, eq. 1); the
optimizer then weighs it by message size (eq. 2) so that a large stream's priority claims
bandwidth in proportion to what it costs.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from dbml.core.errors import SpecError
from dbml.core.spec import check_number

__all__ = [
    "collision_priority",
    "linear_ramp",
    "normalize_priorities",
    "time_to_collision_s",
]

CRITICAL_TC_S = 3.0
"""Below this time to collision the camera gets full priority (paper, eq. 7)."""
SAFE_TC_S = 20.0
"""Above this time to collision the camera gets no priority (paper, eq. 7)."""


def _non_negative(name: str, value: float) -> float:
    return check_number(value, field=name, minimum=0, finite=False)


def time_to_collision_s(distance_m: float, speed_m_per_s: float) -> float:
    """Expected time before collision, ``distance / speed`` (eq. 6); a stopped robot never collides.

    >>> time_to_collision_s(1.25, 0.125)
    10.0
    >>> time_to_collision_s(1.0, 0.0)
    inf
    """
    distance = _non_negative("distance_m", distance_m)
    speed = _non_negative("speed_m_per_s", speed_m_per_s)
    if speed == 0.0:
        return math.inf
    return distance / speed


def linear_ramp(value: float, *, full_at: float, zero_at: float) -> float:
    """Priority 1 at ``full_at``, 0 at ``zero_at``, linear between and clamped outside.

    Works in both directions: ``full_at < zero_at`` for "closer is more urgent" (time to
    collision), ``full_at > zero_at`` for "more is more urgent" (a detector's confidence).
    """
    check_number(value, field="value", finite=False)
    if not (math.isfinite(full_at) and math.isfinite(zero_at)) or full_at == zero_at:
        raise SpecError(f"ramp full_at={full_at!r}, zero_at={zero_at!r} must differ and be finite")
    fraction = (zero_at - value) / (zero_at - full_at)
    return min(1.0, max(0.0, fraction))


def collision_priority(
    tc_s: float, *, critical_s: float = CRITICAL_TC_S, safe_s: float = SAFE_TC_S
) -> float:
    """The paper's camera priority from the time to collision (eq. 7).

    ``1`` if ``tc < critical_s``, ``0`` if ``tc > safe_s``, else
    ``(safe_s - tc) / (safe_s - critical_s)``; ``tc = inf`` (a stopped robot) gives 0.
    """
    tc = _non_negative("tc_s", tc_s)
    if not critical_s < safe_s:
        raise SpecError(f"critical_s={critical_s!r} must be below safe_s={safe_s!r}")
    return linear_ramp(tc, full_at=critical_s, zero_at=safe_s)


def normalize_priorities(
    priorities: npt.ArrayLike, sizes_bytes: npt.ArrayLike
) -> npt.NDArray[np.float64]:
    """Size-weighted normalisation (eq. 2): ``p'_i = p_i w_i / sum_k p_k w_k``, or all 0."""
    p = np.asarray(priorities, dtype=float)
    w = np.asarray(sizes_bytes, dtype=float)
    if p.shape != w.shape:
        raise SpecError(f"priorities shape {p.shape} does not match sizes shape {w.shape}")
    total = float(p @ w)
    if total <= 0.0:
        return np.zeros_like(w)
    normalized: npt.NDArray[np.float64] = p * w / total
    return normalized
