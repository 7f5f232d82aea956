"""Which increases a round pushes before every decrease is acknowledged: pure bookkeeping."""

from __future__ import annotations

import random

from hypothesis import given
from hypothesis import strategies as st

from dbml.runtime.admission import Admission

SIZE = 1000.0


def test_an_increase_waits_for_the_decrease_that_makes_its_room() -> None:
    admission = Admission.start(
        budget_bytes_per_s=10 * SIZE,
        running_hz={"/a": 10.0, "/b": 0.0},
        new_hz={"/b": 4.0},
        sizes_bytes={"/a": SIZE, "/b": SIZE},
    )
    assert admission.covered() == []  # /a still counts at 10 Hz: no room
    admission.acknowledged("/a", before_hz=10.0, after_hz=6.0, size=SIZE)
    assert admission.covered() == ["/b"]
    assert admission.rest() == []


def test_a_slow_publisher_holds_back_only_what_its_decrease_covers() -> None:
    """The fast decreases' room admits what it covers; the rest waits for the slow one."""
    admission = Admission.start(
        budget_bytes_per_s=20 * SIZE,
        running_hz={"/fast": 10.0, "/slow": 10.0},
        new_hz={"/new1": 5.0, "/new2": 5.0},
        sizes_bytes={"/fast": SIZE, "/slow": SIZE, "/new1": SIZE, "/new2": SIZE},
    )
    admission.acknowledged("/fast", before_hz=10.0, after_hz=5.0, size=SIZE)
    assert admission.covered() == ["/new1"]
    assert admission.rest() == ["/new2"]
    admission.acknowledged("/slow", before_hz=10.0, after_hz=5.0, size=SIZE)
    assert admission.covered() == ["/new2"]


def test_room_left_unused_admits_a_new_channel_at_once() -> None:
    admission = Admission.start(
        budget_bytes_per_s=10 * SIZE,
        running_hz={"/a": 2.0},
        new_hz={"/b": 5.0},
        sizes_bytes={"/a": SIZE, "/b": SIZE},
    )
    assert admission.covered() == ["/b"]


@given(
    st.lists(
        st.tuples(st.floats(0.0, 16.0), st.floats(0.0, 16.0), st.floats(1.0, 100_000.0)),
        min_size=1,
        max_size=30,
    ),
    st.randoms(use_true_random=False),
)
def test_what_is_pushed_never_exceeds_the_budget_while_decreases_are_in_flight(
    changes: list[tuple[float, float, float]], rng: object
) -> None:
    """Whatever the order of the acknowledgements, what was told stays within the budget.

    Every decrease counts at its old rate until acknowledged.
    """
    assert isinstance(rng, random.Random)
    topics = [f"/c{k}" for k in range(len(changes))]
    running = {t: before for t, (before, _, _) in zip(topics, changes, strict=True)}
    new = {t: after for t, (_, after, _) in zip(topics, changes, strict=True)}
    sizes = {t: size for t, (_, _, size) in zip(topics, changes, strict=True)}
    budget = sum(max(running[t], new[t]) * sizes[t] for t in topics) * rng.uniform(0.5, 1.0)
    budget = max(budget, sum(running[t] * sizes[t] for t in topics))  # it fits before
    admission = Admission.start(
        budget_bytes_per_s=budget, running_hz=running, new_hz=new, sizes_bytes=sizes
    )
    told = dict(running)  # the higher of told and in force, per channel
    decreases = [t for t in topics if new[t] < running[t]]
    rng.shuffle(decreases)
    for topic in [None, *decreases]:
        if topic is not None:
            admission.acknowledged(
                topic, before_hz=running[topic], after_hz=new[topic], size=sizes[topic]
            )
            told[topic] = new[topic]
        for pushed in admission.covered():
            told[pushed] = new[pushed]
        assert sum(told[t] * sizes[t] for t in topics) <= budget * (1 + 1e-9)
    assert admission.rest() == sorted(
        t for t in topics if new[t] > running[t] and t not in admission.pushed
    )
