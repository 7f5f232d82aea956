"""Invariants of every strategy, checked on random fleets against an independent HiGHS model."""

import random

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.optimize import linprog

from dbml.core import ChannelSpec, LinkSpec, Problem, Status, Strategy, allocate

TOL = 1e-9


@st.composite
def problems(
    draw: st.DrawFn, *, max_channels: int = 8, with_links: bool = False, feasible: bool = False
) -> Problem:
    n = draw(st.integers(1, max_channels))
    channels = []
    for i in range(n):
        fmin = draw(st.floats(0.1, 20))
        fmax = fmin + draw(st.floats(0, 30))
        size = draw(st.sampled_from([100.0, 1000.0, 21_000.0, 84_000.0]) | st.floats(1, 1e5))
        priority = draw(st.floats(0, 1))
        channels.append(ChannelSpec(f"/c{i}", fmin, fmax, size, priority))
    need_max = sum(c.max_rate_hz * c.size_bytes for c in channels) / 125_000
    utilization = draw(st.sampled_from([1.0, 0.8]) | st.floats(0.05, 1.0))
    if feasible:
        w, _, _, floors = columns(Problem(tuple(channels), 1.0))
        low = float(w @ floors) / 125_000 / utilization * (1 + 1e-6)
        high = max(low, 1.2 * need_max / utilization)
        bandwidth = low + draw(st.floats(0, 1)) * (high - low)
    else:
        bandwidth = draw(st.floats(1e-3, 1.2)) * need_max
    links: list[LinkSpec] = []
    if with_links:
        for k in range(draw(st.integers(0, 3))):
            members = draw(
                st.lists(st.sampled_from([c.topic for c in channels]), min_size=1, unique=True)
            )
            links.append(LinkSpec(f"l{k}", draw(st.floats(0.05, 1.0)) * bandwidth, tuple(members)))
    return Problem(tuple(channels), bandwidth, utilization, tuple(links))


def columns(problem: Problem) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Sizes, minimums, maximums and the eq. 2/4 floors, computed here independently."""
    w = np.array([c.size_bytes for c in problem.channels])
    fmin = np.array([c.min_rate_hz for c in problem.channels])
    fmax = np.array([c.max_rate_hz for c in problem.channels])
    p = np.array([c.priority for c in problem.channels])
    weighted = p * w
    normalized = weighted / weighted.sum() if weighted.sum() > 0 else np.zeros_like(w)
    return w, fmin, fmax, fmin + (fmax - fmin) * normalized


def rows(problem: Problem) -> tuple[np.ndarray, np.ndarray]:
    w = np.array([c.size_bytes for c in problem.channels])
    topics = [c.topic for c in problem.channels]
    a = [w]
    b = [problem.budget_bytes_per_s]
    for link in problem.links:
        a.append(np.array([w[i] if t in link.topics else 0.0 for i, t in enumerate(topics)]))
        b.append(link.capacity_mbit * 125_000 * problem.utilization)
    return np.array(a), np.array(b)


def highs_optimum(problem: Problem, floors: np.ndarray) -> float | None:
    """The eq. 5 optimum by HiGHS, or None when the floors do not fit."""
    w, _, fmax, _ = columns(problem)
    a, b = rows(problem)
    result = linprog(
        -w, A_ub=a, b_ub=b, bounds=list(zip(floors, fmax, strict=True)), method="highs"
    )
    return float(w @ result.x) if result.status == 0 else None


@pytest.mark.parametrize("strategy", list(Strategy))
@given(problem=problems())
@settings(max_examples=150, deadline=None)
def test_never_exceeds_the_budget(strategy: Strategy, problem: Problem) -> None:
    allocation = allocate(problem, strategy=strategy)
    assert allocation.total_bytes_per_s <= problem.budget_bytes_per_s * (1 + TOL)
    assert np.all(allocation.rate_hz > 0)


@pytest.mark.parametrize("strategy", list(Strategy))
@given(problem=problems())
@settings(max_examples=150, deadline=None)
def test_feasible_rates_within_bounds(strategy: Strategy, problem: Problem) -> None:
    allocation = allocate(problem, strategy=strategy)
    w, fmin, fmax, floors = columns(problem)
    lower = fmin if strategy is Strategy.STATIC else floors
    fits = w @ lower <= problem.budget_bytes_per_s * (1 - 1e-9)
    assume(fits or w @ lower > problem.budget_bytes_per_s * (1 + 1e-9))
    assert (allocation.status is Status.OPTIMAL) == fits
    if fits:
        assert np.all(allocation.rate_hz >= lower * (1 - TOL))
        assert np.all(allocation.rate_hz <= fmax * (1 + TOL))


@pytest.mark.parametrize("strategy", [Strategy.PAPER, Strategy.LP])
@given(problem=problems(feasible=True))
@settings(max_examples=150, deadline=None)
def test_reaches_the_lp_optimum(strategy: Strategy, problem: Problem) -> None:
    _, _, _, floors = columns(problem)
    best = highs_optimum(problem, floors)
    assert best is not None
    allocation = allocate(problem, strategy=strategy)
    assert allocation.total_bytes_per_s == pytest.approx(best, rel=1e-7)


@given(problem=problems(with_links=True))
@settings(max_examples=150, deadline=None)
def test_lp_with_links_reaches_the_optimum_and_respects_every_link(problem: Problem) -> None:
    allocation = allocate(problem, strategy=Strategy.LP)
    a, b = rows(problem)
    assert np.all(a @ allocation.rate_hz <= b * (1 + 1e-7))
    _, _, _, floors = columns(problem)
    best = highs_optimum(problem, floors)
    if best is not None:
        assert allocation.status is Status.OPTIMAL
        assert allocation.total_bytes_per_s == pytest.approx(best, rel=1e-6)


@given(problem=problems())
@settings(max_examples=150, deadline=None)
def test_lp_without_links_is_paper(problem: Problem) -> None:
    np.testing.assert_array_equal(
        allocate(problem, strategy="lp").rate_hz, allocate(problem, strategy="paper").rate_hz
    )


@given(problem=problems(feasible=True))
@settings(max_examples=200, deadline=None)
def test_paper_tie_break_smallest_message_first_then_declaration_order(problem: Problem) -> None:
    allocation = allocate(problem, strategy=Strategy.PAPER)
    assert allocation.status is Status.OPTIMAL
    w, _, fmax, floors = columns(problem)
    rates = allocation.rate_hz
    raised = rates > floors * (1 + 1e-9) + 1e-12
    below_max = rates < fmax * (1 - 1e-9)
    # At most one channel is left part-way; every channel that comes before a raised one in
    # (size, declaration) order is already at its maximum.
    assert np.count_nonzero(raised & below_max) <= 1
    for j in np.flatnonzero(raised):
        for i in range(len(w)):
            if (w[i], i) < (w[j], j):
                assert not below_max[i], (i, j)


@given(problem=problems(), index=st.integers(0, 7), bump=st.floats(0, 1))
@settings(max_examples=150, deadline=None)
def test_raising_a_priority_never_lowers_its_floor(
    problem: Problem, index: int, bump: float
) -> None:
    index %= len(problem.channels)
    channels = list(problem.channels)
    old = channels[index]
    channels[index] = ChannelSpec(
        old.topic, old.min_rate_hz, old.max_rate_hz, old.size_bytes, min(1.0, old.priority + bump)
    )
    raised = Problem(tuple(channels), problem.bandwidth_mbit, problem.utilization)
    for strategy in (Strategy.PAPER, Strategy.FAIR, Strategy.LP):
        before = allocate(problem, strategy=strategy).floor_hz[index]
        after = allocate(raised, strategy=strategy).floor_hz[index]
        assert after >= before * (1 - 1e-12)


@pytest.mark.parametrize("strategy", list(Strategy))
@given(problem=problems())
@settings(max_examples=150, deadline=None)
def test_infeasible_still_fits_and_says_what_is_needed(
    strategy: Strategy, problem: Problem
) -> None:
    allocation = allocate(problem, strategy=strategy)
    assume(allocation.status is Status.INFEASIBLE)
    assert allocation.total_bytes_per_s <= problem.budget_bytes_per_s * (1 + TOL)
    assert " need " in allocation.message
    assert "Mbit/s but the budget allows" in allocation.message
    w, fmin, _, _ = columns(problem)
    if w @ fmin <= problem.budget_bytes_per_s:
        assert np.all(allocation.rate_hz >= fmin * (1 - TOL))
    else:
        fraction = allocation.rate_hz / fmin
        np.testing.assert_allclose(fraction, fraction[0], rtol=1e-9)


@given(problem=problems(feasible=True))
@settings(max_examples=150, deadline=None)
def test_fair_raises_the_lowest_rates_first(problem: Problem) -> None:
    allocation = allocate(problem, strategy=Strategy.FAIR)
    assert allocation.status is Status.OPTIMAL
    _, _, fmax, floors = columns(problem)
    rates = allocation.rate_hz
    raised = rates > floors * (1 + 1e-9)
    # Every channel above its floor sits at one common level, and nobody below it could rise.
    if raised.any():
        level = rates[raised].max()
        np.testing.assert_allclose(rates[raised & (rates < fmax * (1 - 1e-9))], level, rtol=1e-9)
        assert np.all((rates >= level * (1 - 1e-9)) | (rates >= fmax * (1 - 1e-9)))


@settings(max_examples=200, deadline=None)
@given(
    st.lists(
        st.tuples(st.integers(500, 100_000), st.floats(0.0, 1.0), st.floats(0.0, 1.0)),
        min_size=2,
        max_size=8,
    ),
    st.floats(2.0, 50.0),
    st.randoms(use_true_random=False),
)
def test_with_frame_headroom_every_window_of_whole_frames_fits_budget_plus_one_message(
    rows: list[tuple[int, float, float]], mbit: float, rng: random.Random
) -> None:
    """Periodic frames at the allocated rates, any phases: no 1-s window over B + max size."""
    channels = tuple(
        ChannelSpec(f"/c{i}", 1.0, 16.0, size, priority)
        for i, (size, priority, _) in enumerate(rows)
    )
    problem = Problem(channels, bandwidth_mbit=mbit, frame_headroom=True)
    allocation = allocate(problem)
    budget = mbit * 125_000
    if allocation.status is not Status.OPTIMAL or problem.headroom_bytes_per_s < sum(
        c.size_bytes for c in channels
    ) - max(c.size_bytes for c in channels):
        return  # the headroom is capped (a budget smaller than the frames): no promise
    horizon_s = 5.0
    frames: list[tuple[float, float]] = []
    for channel, rate in zip(channels, allocation.rate_hz, strict=True):
        phase = rng.random() / rate
        frames += [(phase + k / rate, channel.size_bytes) for k in range(int(horizon_s * rate) + 1)]
    frames.sort()
    largest = max(c.size_bytes for c in channels)
    for start, _ in frames:
        window = sum(size for t, size in frames if start <= t < start + 1.0)
        assert window <= budget + largest + 1e-6


def test_frame_headroom_is_off_by_default_and_keeps_back_all_but_the_largest_message() -> None:
    channels = (
        ChannelSpec("/a", 1, 16, 84_000, 0.0),
        ChannelSpec("/b", 1, 16, 21_000, 0.0),
        ChannelSpec("/c", 1, 16, 8_000, 0.0),
    )
    plain = Problem(channels, bandwidth_mbit=11)
    kept = Problem(channels, bandwidth_mbit=11, frame_headroom=True)
    assert plain.budget_bytes_per_s == 1_375_000
    assert kept.headroom_bytes_per_s == 29_000
    assert kept.budget_bytes_per_s == 1_346_000
    assert "kept for whole frames" in allocate(kept).message
