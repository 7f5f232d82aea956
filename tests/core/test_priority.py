import math

import numpy as np
import pytest

from dbml.core import (
    SpecError,
    collision_priority,
    linear_ramp,
    normalize_priorities,
    time_to_collision_s,
)


def test_time_to_collision_is_distance_over_speed() -> None:
    assert time_to_collision_s(2.0, 0.5) == 4.0
    assert time_to_collision_s(0.0, 0.5) == 0.0


def test_stopped_robot_never_collides() -> None:
    assert time_to_collision_s(1.0, 0.0) == math.inf
    assert collision_priority(math.inf) == 0.0


@pytest.mark.parametrize(
    ("distance", "speed", "message"),
    [
        (-1.0, 1.0, r"^distance_m=-1.0 must be >= 0$"),
        (1.0, -0.1, r"^speed_m_per_s=-0.1 must be >= 0$"),
        (math.nan, 1.0, r"^distance_m=nan is not a number$"),
        (1.0, math.nan, r"^speed_m_per_s=nan is not a number$"),
    ],
)
def test_time_to_collision_rejects_negative_or_nan(
    distance: float, speed: float, message: str
) -> None:
    with pytest.raises(SpecError, match=message):
        time_to_collision_s(distance, speed)


@pytest.mark.parametrize(
    ("tc_s", "expected"),
    [
        (0.0, 1.0),
        (2.5, 1.0),
        (3.0, 1.0),
        (10.0, 10 / 17),
        (15.0, 5 / 17),
        (20.0, 0.0),
        (20.1, 0.0),
        (100.0, 0.0),
    ],
)
def test_collision_priority_follows_eq7(tc_s: float, expected: float) -> None:
    assert collision_priority(tc_s) == pytest.approx(expected, abs=1e-15)


@pytest.mark.parametrize(
    ("tc_s", "message"),
    [(-1.0, r"^tc_s=-1.0 must be >= 0$"), (math.nan, r"^tc_s=nan is not a number$")],
)
def test_collision_priority_rejects_negative_or_nan(tc_s: float, message: str) -> None:
    with pytest.raises(SpecError, match=message):
        collision_priority(tc_s)


def test_collision_priority_thresholds_are_configurable_and_checked() -> None:
    assert collision_priority(5.0, critical_s=1.0, safe_s=9.0) == 0.5
    with pytest.raises(SpecError, match=r"critical_s=9.0 must be below safe_s=1.0"):
        collision_priority(5.0, critical_s=9.0, safe_s=1.0)


def test_linear_ramp_both_directions_and_clamped() -> None:
    rising = {"full_at": 0.9, "zero_at": 0.1}
    assert linear_ramp(0.5, **rising) == pytest.approx(0.5)
    assert linear_ramp(1.0, **rising) == 1.0
    assert linear_ramp(0.0, **rising) == 0.0
    falling = {"full_at": 3.0, "zero_at": 20.0}
    assert linear_ramp(11.5, **falling) == pytest.approx(0.5)
    with pytest.raises(SpecError, match=r"ramp full_at=1.0, zero_at=1.0 must differ"):
        linear_ramp(0.5, full_at=1.0, zero_at=1.0)
    with pytest.raises(SpecError, match=r"value=nan is not a number"):
        linear_ramp(math.nan, **rising)


def test_normalisation_weighs_by_size_eq2() -> None:
    # Step 6 of Table 2: equal raw priorities, sizes 84,000 and 21,000 -> 0.8 / 0.2.
    normalized = normalize_priorities([5 / 17, 5 / 17], [84_000, 21_000])
    np.testing.assert_allclose(normalized, [0.8, 0.2])
    np.testing.assert_array_equal(normalize_priorities([0.0, 0.0], [1.0, 2.0]), [0.0, 0.0])


def test_normalisation_rejects_mismatched_shapes() -> None:
    with pytest.raises(
        SpecError, match=r"priorities shape \(2,\) does not match sizes shape \(3,\)"
    ):
        normalize_priorities([0.1, 0.2], [1.0, 2.0, 3.0])
