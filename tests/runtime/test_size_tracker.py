"""The size the optimizer is told: the first, then only a material change; a forged one disputed."""

from __future__ import annotations

import pytest

from dbml.runtime.size import SIZE_CHANGE, SizeTracker

FRAME_BYTES = 84_000


def test_the_first_size_is_announced() -> None:
    sizes = SizeTracker()
    assert sizes.known_bytes == -1
    assert sizes.observe(FRAME_BYTES)
    assert sizes.known_bytes == FRAME_BYTES


@pytest.mark.parametrize(
    ("size_bytes", "announced"),
    [
        (FRAME_BYTES, False),
        (round(FRAME_BYTES * (1 + SIZE_CHANGE)), False),  # the bound itself is a wobble
        (round(FRAME_BYTES * (1 - SIZE_CHANGE)), False),
        (round(FRAME_BYTES * (1 + SIZE_CHANGE)) + 1, True),
        (round(FRAME_BYTES * (1 - SIZE_CHANGE)) - 1, True),
    ],
)
def test_only_a_material_change_is_announced(size_bytes: int, announced: bool) -> None:
    sizes = SizeTracker()
    sizes.observe(FRAME_BYTES)
    assert sizes.observe(size_bytes) is announced
    assert sizes.known_bytes == (size_bytes if announced else FRAME_BYTES)


def test_small_steps_are_measured_against_the_size_announced() -> None:
    sizes = SizeTracker()
    sizes.observe(100_000)
    steps = [104_000, 108_000, 111_000]  # each within 10 % of the last, not of the announced
    assert [sizes.observe(s) for s in steps] == [False, False, True]


def test_a_size_written_by_someone_else_is_disputed_and_announced_again() -> None:
    sizes = SizeTracker()
    assert sizes.dispute(1.0) is None  # no size of ours yet: nothing to dispute with
    sizes.observe(FRAME_BYTES)
    assert sizes.dispute(float(FRAME_BYTES)) is None  # our own write, echoed
    assert sizes.dispute(1.0) == FRAME_BYTES
    assert sizes.observe(FRAME_BYTES)  # the next message re-asserts it


def test_a_deleted_size_is_disputed() -> None:
    sizes = SizeTracker()
    sizes.observe(FRAME_BYTES)
    assert sizes.dispute(None) == FRAME_BYTES
