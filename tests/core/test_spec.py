import math
from typing import Any

import pytest

from dbml.core import ChannelSpec, LinkSpec, Problem, SpecError


def camera(topic: str = "/r1/camera", **overrides: float) -> ChannelSpec:
    values = {"min_rate_hz": 1.0, "max_rate_hz": 16.0, "size_bytes": 84_000.0, "priority": 0.0}
    values.update(overrides)
    return ChannelSpec(topic, **values)


def test_channel_normalises_numbers_to_float() -> None:
    channel = ChannelSpec("/a", 1, 16, 84_000, 1)
    assert channel.min_rate_hz == 1.0
    assert isinstance(channel.size_bytes, float)
    assert isinstance(channel.priority, float)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (
            {"min_rate_hz": 30.0, "max_rate_hz": 10.0},
            r"frequency.min=30.0 exceeds frequency.max=10.0",
        ),
        ({"min_rate_hz": 0.0}, r"frequency.min=0.0 must be > 0"),
        ({"min_rate_hz": -1.0}, r"frequency.min=-1.0 must be > 0"),
        ({"size_bytes": 0.0}, r"message_size_in_bytes=0.0 must be > 0"),
        ({"priority": 1.5}, r"priority=1.5 must be within \[0, 1\]"),
        ({"priority": -0.1}, r"priority=-0.1 must be within \[0, 1\]"),
        ({"max_rate_hz": math.inf}, r"frequency.max=inf is not finite"),
        ({"priority": math.nan}, r"priority=nan is not finite"),
    ],
)
def test_channel_rejects_bad_values_naming_channel_and_field(
    overrides: dict[str, Any], message: str
) -> None:
    with pytest.raises(SpecError, match=r"channel '/r1/camera': " + message):
        camera(**overrides)


def test_channel_rejects_non_numbers_and_empty_topic() -> None:
    with pytest.raises(SpecError, match=r"channel '/a': frequency.min='1' is not a number"):
        ChannelSpec("/a", "1", 16, 10)  # type: ignore[arg-type]
    with pytest.raises(SpecError, match=r"frequency.max=True is not a number"):
        ChannelSpec("/a", 1, True, 10)
    with pytest.raises(SpecError, match=r"channel topic='' must be a non-empty string"):
        ChannelSpec("", 1, 16, 10)


def test_link_validation() -> None:
    with pytest.raises(SpecError, match=r"link 'up': max_bandwidth_in_mbit=0.0 must be > 0"):
        LinkSpec("up", 0.0, ("/a",))
    with pytest.raises(SpecError, match=r"link 'up': channels=\[\] must name at least one"):
        LinkSpec("up", 1.0, ())
    with pytest.raises(
        SpecError, match=r"link 'up': channels=\['/a', '/a'\] lists a channel twice"
    ):
        LinkSpec("up", 1.0, ("/a", "/a"))
    with pytest.raises(SpecError, match=r"link name='' must be a non-empty string"):
        LinkSpec("", 1.0, ("/a",))


def test_problem_budget_uses_decimal_megabits_and_utilization() -> None:
    problem = Problem((camera(),), bandwidth_mbit=11, utilization=0.5)
    assert problem.link_bytes_per_s == 1_375_000.0
    assert problem.budget_bytes_per_s == 687_500.0


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"bandwidth_mbit": 0.0}, r"problem: max_bandwidth_in_mbit=0.0 must be > 0"),
        (
            {"bandwidth_mbit": 11, "utilization": 0.0},
            r"max_bandwidth_utilization=0.0 must be within",
        ),
        (
            {"bandwidth_mbit": 11, "utilization": 1.2},
            r"max_bandwidth_utilization=1.2 must be within",
        ),
    ],
)
def test_problem_rejects_bad_budget(kwargs: dict[str, Any], message: str) -> None:
    with pytest.raises(SpecError, match=message):
        Problem((camera(),), **kwargs)


def test_problem_rejects_duplicates_unknown_topics_and_emptiness() -> None:
    with pytest.raises(
        SpecError, match=r"channel '/r1/camera': topic='/r1/camera' is declared twice"
    ):
        Problem((camera(), camera()), bandwidth_mbit=11)
    with pytest.raises(SpecError, match=r"problem: channels=\[\] must hold at least one channel"):
        Problem((), bandwidth_mbit=11)
    with pytest.raises(SpecError, match=r"link 'up': channels lists unknown topic '/nope'"):
        Problem((camera(),), bandwidth_mbit=11, links=(LinkSpec("up", 1.0, ("/nope",)),))
    link = LinkSpec("up", 1.0, ("/r1/camera",))
    with pytest.raises(SpecError, match=r"link 'up': name='up' is declared twice"):
        Problem((camera(),), bandwidth_mbit=11, links=(link, link))


def test_specs_are_frozen() -> None:
    channel = camera()
    with pytest.raises(AttributeError):
        channel.priority = 1.0  # type: ignore[misc]
