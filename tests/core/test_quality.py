"""The quality allocation: a rung and a rate per channel, against scipy's exact MILP (HiGHS).

The utility is re-derived here from the documented model (dbml.core.quality's docstring), not
read from the code under test; the reference optimum is ``scipy.optimize.milp`` over every
allowed rung at a grid of rates, so it can only be at or below the continuous optimum.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy.optimize import Bounds, LinearConstraint, milp
from scipy.sparse import coo_array

from dbml.core.errors import SpecError
from dbml.core.ladder import MAX_RUNGS, Ladder, Preference, Rung
from dbml.core.quality import QualityStatus, allocate_quality, channel_utility
from dbml.core.spec import ChannelSpec, LinkSpec, Problem

# A 640x480 photograph's JPEG ladder (../shared/QUALITY.md): (scale, quality, bytes, SSIM).
PHOTO = (
    (1.0, 10, 15_871, 0.835), (1.0, 30, 30_488, 0.925), (1.0, 50, 41_227, 0.950),
    (1.0, 70, 55_379, 0.966), (1.0, 80, 68_925, 0.976), (1.0, 90, 100_519, 0.987),
    (1.0, 95, 142_770, 0.993), (0.5, 50, 13_557, 0.834), (0.5, 80, 22_543, 0.871),
    (0.5, 95, 45_121, 0.893), (0.25, 50, 4_495, 0.647), (0.25, 80, 7_205, 0.694),
    (0.25, 95, 13_716, 0.719),
)  # fmt: skip
TERMS = {"balanced": (1.0, 1.0), "keep_rate": (1.0, None), "keep_detail": (8.0, 0.25)}
"""The documented (gamma, knee Hz) per preference; None: the channel's maximum rate."""
GAP = 0.005
"""The solver is within 0.5 % of the exact optimum (the issue's bound)."""


def photo_ladder(scale_bytes: float = 1.0, **options: object) -> Ladder:
    return Ladder(
        tuple(Rung(b * scale_bytes, q, scale=s, jpeg_quality=j) for s, j, b, q in PHOTO),
        **options,  # type: ignore[arg-type]
    )


def floors_of(problem: Problem) -> np.ndarray:
    a = problem.arrays
    weighted = a.priority * a.size_bytes
    norm = weighted / weighted.sum() if weighted.sum() > 0 else np.zeros_like(weighted)
    return (a.max_rate_hz - a.min_rate_hz) * norm + a.min_rate_hz


def value(problem: Problem, ladder: Ladder | None, i: int, rung: Rung, rate: float) -> float:
    """One channel's utility, from the documented formula."""
    a = problem.arrays
    weighted = a.priority * a.size_bytes
    norm = weighted[i] / weighted.sum() if weighted.sum() > 0 else 0.0
    gamma, knee = TERMS[ladder.preference.value] if ladder else (1.0, 1.0)
    knee = float(a.max_rate_hz[i]) if knee is None else knee
    return float(
        (0.1 + norm)
        * rung.quality**gamma
        * math.log1p(rate / knee)
        / math.log1p(float(a.max_rate_hz[i]) / knee)
    )


def allowed(ladder: Ladder | None, size: float) -> list[Rung]:
    if ladder is None:
        return [Rung(size, 1.0)]
    kept = [r for r in ladder.rungs if r.quality >= ladder.min_quality]
    return kept or [max(ladder.rungs, key=lambda r: r.quality)]


def milp_optimum(problem: Problem, ladders: dict[str, Ladder], grid: int = 33) -> float:
    """The best utility over every allowed rung at ``grid`` rates from floor to maximum."""
    floors = floors_of(problem)
    costs, values, owners = [], [], []
    for i, topic in enumerate(problem.topics):
        ladder = ladders.get(topic)
        for rung in allowed(ladder, float(problem.arrays.size_bytes[i])):
            for rate in np.linspace(floors[i], problem.arrays.max_rate_hz[i], grid):
                costs.append(rate * rung.size_bytes)
                values.append(value(problem, ladder, i, rung, float(rate)))
                owners.append(i)
    k, n = len(costs), len(problem.topics)
    one = coo_array((np.ones(k), (owners, np.arange(k))), shape=(n, k))
    constraints = [
        LinearConstraint(one, 1, 1),
        LinearConstraint(np.array([costs]), -np.inf, problem.budget_bytes_per_s),
    ]
    for link in problem.links:  # a link's capacity (times the utilisation) over its channels
        crossing = {problem.topics.index(t) for t in link.topics}
        row = [c if owner in crossing else 0.0 for c, owner in zip(costs, owners, strict=True)]
        cap = link.capacity_mbit * 125_000 * problem.utilization
        constraints.append(LinearConstraint(np.array([row]), -np.inf, cap))
    result = milp(
        -np.array(values),
        integrality=np.ones(k, dtype=np.int64),
        bounds=Bounds(0, 1),
        constraints=constraints,
    )
    assert result.success, result.message
    return float(-result.fun)


def achieved(problem: Problem, ladders: dict[str, Ladder], allocation: object) -> float:
    """The allocation's utility by the documented formula, its rungs checked as allowed."""
    total = 0.0
    for i, topic in enumerate(problem.topics):
        ladder = ladders.get(topic)
        j = int(allocation.rung[i])  # type: ignore[attr-defined]
        rung = Rung(float(problem.arrays.size_bytes[i]), 1.0) if j < 0 else ladder.rungs[j]  # type: ignore[union-attr]
        assert rung in allowed(ladder, float(problem.arrays.size_bytes[i]))
        total += value(problem, ladder, i, rung, float(allocation.rate_hz[i]))  # type: ignore[attr-defined]
    return total


def random_instance(rng: np.random.Generator, n: int) -> tuple[Problem, dict[str, Ladder]]:
    channels, ladders = [], {}
    for i in range(n):
        scale = float(rng.uniform(0.5, 1.5))
        fmin = float(rng.choice([1.0, 2.0, 5.0]))
        topic = f"/r{i}/camera"
        priority = float(rng.uniform(0, 1)) if rng.uniform() < 0.5 else 0.0
        channels.append(ChannelSpec(topic, fmin, 16.0, 84_000 * scale, priority))
        if rng.uniform() < 0.85:
            preference = rng.choice(list(Preference))
            ladders[topic] = photo_ladder(
                scale, preference=preference, min_quality=float(rng.choice([0.0, 0.0, 0.9]))
            )
    # A budget between what the floors need on the cheapest rungs and three times that: feasible.
    probe = Problem(tuple(channels), 1.0)
    need = sum(
        floor * min(r.size_bytes for r in allowed(ladders.get(c.topic), c.size_bytes))
        for floor, c in zip(floors_of(probe), channels, strict=True)
    )
    bandwidth = need * float(rng.uniform(1.02, 3.0)) * 8 / 1e6
    return Problem(tuple(channels), bandwidth), ladders


@pytest.mark.parametrize(
    ("seed", "n"),
    [(seed, n) for n in (1, 2, 3, 5, 8, 12) for seed in range(4)]
    + [(0, 24), (1, 40), (0, 72), (1, 96)],  # past 64 channels: the fixed point's path
)
def test_within_half_a_percent_of_milp_on_random_fleets(seed: int, n: int) -> None:
    rng = np.random.default_rng(seed * 100 + n)
    problem, ladders = random_instance(rng, n)
    allocation = allocate_quality(problem, ladders)
    assert allocation.status is QualityStatus.OPTIMAL, allocation.message
    assert allocation.total_bytes_per_s <= problem.budget_bytes_per_s * (1 + 1e-9)
    ours = achieved(problem, ladders, allocation)
    assert ours == pytest.approx(allocation.utility, rel=1e-9)
    reference = milp_optimum(problem, ladders)
    assert ours >= reference * (1 - GAP), (ours, reference)
    assert allocation.upper_bound is not None
    assert ours <= allocation.upper_bound * (1 + 1e-9)


def test_the_paper_cameras_at_16_hz_with_the_prioritised_one_sharper() -> None:
    """Table 2, step 1 (R2 prioritised) on 11 Mbit/s: both fit at 16 Hz as JPEG."""
    problem = Problem(
        (
            ChannelSpec("/r1/camera", 1, 16, 84_000, 0.0),
            ChannelSpec("/r2/camera", 1, 16, 21_000, 10 / 17),
        ),
        11,
    )
    ladders = {"/r1/camera": photo_ladder(), "/r2/camera": photo_ladder()}
    allocation = allocate_quality(problem, ladders)
    assert allocation.status is QualityStatus.OPTIMAL
    assert list(allocation.rate_hz) == [16.0, 16.0]
    assert allocation.quality[1] > allocation.quality[0]
    assert allocation.total_bytes_per_s <= problem.budget_bytes_per_s
    assert achieved(problem, ladders, allocation) >= milp_optimum(problem, ladders) * (1 - GAP)


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(1, 6),
    seed=st.integers(0, 2**32 - 1),
    bandwidth=st.floats(0.05, 40),
)
def test_the_budget_the_floors_and_the_quality_floors_hold(
    n: int, seed: int, bandwidth: float
) -> None:
    rng = np.random.default_rng(seed)
    problem, ladders = random_instance(rng, n)
    problem = Problem(problem.channels, bandwidth)
    allocation = allocate_quality(problem, ladders)
    assert allocation.total_bytes_per_s <= problem.budget_bytes_per_s * (1 + 1e-9)
    floors = floors_of(problem)
    assert np.all(allocation.rate_hz <= problem.arrays.max_rate_hz + 1e-9)
    if allocation.status is QualityStatus.OPTIMAL:
        assert np.all(allocation.rate_hz >= floors - 1e-9)
    else:
        assert np.all(allocation.rate_hz <= floors + 1e-9)
        assert "budget allows" in allocation.message
    for i, topic in enumerate(problem.topics):
        ladder = ladders.get(topic)
        size = float(problem.arrays.size_bytes[i])
        j = int(allocation.rung[i])
        rung = Rung(size, 1.0) if j < 0 else ladders[topic].rungs[j]
        assert rung in allowed(ladder, size)
        assert allocation.size_bytes[i] == rung.size_bytes
        assert allocation.quality[i] == rung.quality


@settings(max_examples=25, deadline=None)
@given(
    n=st.integers(65, 160),
    seed=st.integers(0, 2**32 - 1),
    headroom=st.floats(1.0, 4.0),
)
def test_a_large_fleet_keeps_the_budget_and_the_floors_and_meets_its_bound(
    n: int, seed: int, headroom: float
) -> None:
    """Past 64 channels the price is found by choosing and filling in turn (a fixed point)."""
    problem, ladders = random_instance(np.random.default_rng(seed), n)
    problem = Problem(problem.channels, problem.bandwidth_mbit * headroom)
    allocation = allocate_quality(problem, ladders)
    assert allocation.status is QualityStatus.OPTIMAL, allocation.message
    assert allocation.total_bytes_per_s <= problem.budget_bytes_per_s * (1 + 1e-9)
    assert np.all(allocation.rate_hz >= floors_of(problem) - 1e-9)
    assert np.all(allocation.rate_hz <= problem.arrays.max_rate_hz + 1e-9)
    ours = achieved(problem, ladders, allocation)
    assert ours == pytest.approx(allocation.utility, rel=1e-9)
    assert allocation.upper_bound is not None
    assert ours <= allocation.upper_bound * (1 + 1e-9)
    assert ours >= allocation.upper_bound * (1 - GAP)  # the Lagrangian's bound: within 0.5 %


@pytest.mark.parametrize("seed", range(4))
def test_the_next_round_from_the_last_price_finds_what_a_cold_solve_finds(seed: int) -> None:
    """``price_hint`` only moves where the search starts: a priority event, then both ways."""
    rng = np.random.default_rng(seed)
    problem, ladders = random_instance(rng, 120)
    first = allocate_quality(problem, ladders)
    assert first.price_per_byte > 0  # the budget binds: a price was paid
    channels = list(problem.channels)
    for i in rng.choice(len(channels), size=3, replace=False):
        c = channels[i]
        channels[i] = ChannelSpec(c.topic, c.min_rate_hz, c.max_rate_hz, c.size_bytes, 0.9)
    moved = Problem(tuple(channels), problem.bandwidth_mbit)
    cold = allocate_quality(moved, ladders)
    for hint in (first.price_per_byte, first.price_per_byte * 100, first.price_per_byte / 100):
        warm = allocate_quality(moved, ladders, price_hint=hint)
        assert warm.utility == pytest.approx(cold.utility, rel=1e-9)
        assert warm.total_bytes_per_s <= moved.budget_bytes_per_s * (1 + 1e-9)


def test_the_price_is_zero_when_every_maximum_fits_and_nan_when_floors_do_not() -> None:
    ladders = {"/r1/camera": photo_ladder()}
    roomy = Problem((ChannelSpec("/r1/camera", 1, 16, 84_000, 0.0),), 100.0)
    assert allocate_quality(roomy, ladders).price_per_byte == 0.0
    short = Problem((ChannelSpec("/r1/camera", 10, 16, 84_000, 0.0),), 0.1)
    allocation = allocate_quality(short, ladders)
    assert allocation.status is QualityStatus.INFEASIBLE
    assert math.isnan(allocation.price_per_byte)


def test_infeasible_floors_take_the_cheapest_rungs_and_keep_the_budget() -> None:
    problem = Problem(
        (ChannelSpec("/a", 10, 16, 84_000, 1.0), ChannelSpec("/b", 10, 16, 84_000, 1.0)), 0.5
    )
    ladders = {"/a": photo_ladder(), "/b": photo_ladder()}
    allocation = allocate_quality(problem, ladders)
    assert allocation.status is QualityStatus.INFEASIBLE
    assert allocation.upper_bound is None
    assert list(allocation.size_bytes) == [4_495, 4_495]
    assert allocation.total_bytes_per_s == pytest.approx(problem.budget_bytes_per_s)
    assert "every channel runs at" in allocation.message


def one_camera(preference: Preference, budget_mbit: float) -> tuple[float, float]:
    problem = Problem((ChannelSpec("/c", 1, 16, 84_000, 0.0),), budget_mbit)
    allocation = allocate_quality(problem, {"/c": photo_ladder(preference=preference)})
    return float(allocation.rate_hz[0]), float(allocation.quality[0])


@pytest.mark.parametrize("budget_mbit", [1.0, 2.0, 3.0, 5.0, 8.0])
def test_keep_rate_gives_up_detail_first_and_keep_detail_frames_first(budget_mbit: float) -> None:
    rate_k, quality_k = one_camera(Preference.KEEP_RATE, budget_mbit)
    rate_b, quality_b = one_camera(Preference.BALANCED, budget_mbit)
    rate_d, quality_d = one_camera(Preference.KEEP_DETAIL, budget_mbit)
    assert rate_k >= rate_b >= rate_d
    assert quality_k <= quality_b <= quality_d
    assert (rate_k, quality_k) != (rate_d, quality_d)  # the preference changes the choice


def test_a_quality_floor_removes_rungs_and_a_floor_none_reaches_keeps_the_best() -> None:
    problem = Problem((ChannelSpec("/c", 1, 16, 84_000, 0.0),), 2.0)
    floor = allocate_quality(problem, {"/c": photo_ladder(min_quality=0.97)})
    assert floor.quality[0] >= 0.97
    unreachable = photo_ladder(min_quality=0.999)
    assert not unreachable.meets_floor
    best = allocate_quality(problem, {"/c": unreachable})
    assert best.quality[0] == 0.993


def test_a_channel_without_a_ladder_keeps_its_size() -> None:
    problem = Problem(
        (ChannelSpec("/a", 1, 16, 84_000, 0.0), ChannelSpec("/b", 1, 16, 21_000, 0.0)), 11
    )
    allocation = allocate_quality(problem, {"/a": photo_ladder()})
    assert allocation.rung[1] == -1
    assert allocation.size_bytes[1] == 21_000
    assert allocation.quality[1] == 1.0


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: Rung(0, 0.5), "rung: size_bytes=0 must be > 0"),
        (lambda: Rung(1000, 1.5), "rung: quality=1.5 must be within [0, 1]"),
        (lambda: Rung(1000, float("nan")), "rung: quality=nan is not finite"),
        (lambda: Rung(1000, 0.5, jpeg_quality=0), "rung: jpeg_quality=0 must be an integer"),
        (lambda: Rung(1000, 0.5, scale=0), "rung: scale=0 must be within (0, 1]"),
        (
            lambda: Ladder(tuple(Rung(1000 + k, 0.5) for k in range(MAX_RUNGS + 1))),
            f"ladder: rungs holds {MAX_RUNGS + 1} rungs, more than {MAX_RUNGS}",
        ),
        (lambda: Ladder(()), "ladder: rungs=[] must hold at least one rung"),
        (lambda: Ladder((Rung(1000, 0.5),), min_quality=2), "ladder: min_quality=2 must be"),
        (
            lambda: Ladder((Rung(1000, 0.5),), preference="sharp"),  # type: ignore[arg-type]
            "ladder: preference='sharp' is not one of: balanced, keep_rate, keep_detail",
        ),
        (
            lambda: allocate_quality(
                Problem((ChannelSpec("/a", 1, 16, 84_000),), 11), {"/b": photo_ladder()}
            ),
            "ladder of topic '/b': no such channel in the problem",
        ),
    ],
)
def test_bad_input_is_one_error_naming_the_field_and_value(make: object, message: str) -> None:
    with pytest.raises(SpecError) as caught:
        make()  # type: ignore[operator]
    assert message in str(caught.value)
    assert "\n" not in str(caught.value)


def test_a_channels_utility_is_the_documented_formula() -> None:
    # keep_detail: gamma 8, knee 0.25 Hz; balanced: gamma 1, knee 1 Hz; keep_rate: knee = fmax.
    detail = channel_utility(
        weight=1.1, quality=0.9, rate_hz=4.0, max_rate_hz=16.0, preference=Preference.KEEP_DETAIL
    )
    assert detail == pytest.approx(1.1 * 0.9**8 * math.log(1 + 16) / math.log(1 + 64))
    plain = channel_utility(weight=0.1, quality=0.5, rate_hz=16.0, max_rate_hz=16.0)
    assert plain == pytest.approx(0.05)
    rate = channel_utility(
        weight=1.0, quality=1.0, rate_hz=8.0, max_rate_hz=16.0, preference=Preference.KEEP_RATE
    )
    assert rate == pytest.approx(math.log(1.5) / math.log(2))


def test_a_rung_worth_nothing_keeps_its_floor_and_the_budget_holds() -> None:
    # A's only rung has quality 0: any byte it spends is worth nothing. With 15,000 B/s, B
    # (1,000 B a frame) can run at its 10 Hz maximum only if A stays at its 1-Hz floor.
    channels = (
        ChannelSpec("/a", 1.0, 10.0, 1_000.0, 0.0),
        ChannelSpec("/b", 1.0, 10.0, 1_000.0, 0.0),
    )
    problem = Problem(channels, 15_000 * 8 / 1e6)
    ladders = {
        "/a": Ladder((Rung(1_000.0, 0.0),)),
        "/b": Ladder((Rung(1_000.0, 0.9),)),
    }
    allocation = allocate_quality(problem, ladders)
    assert allocation.status is QualityStatus.OPTIMAL
    assert allocation.rate_hz.tolist() == pytest.approx([1.0, 10.0])
    assert allocation.total_bytes_per_s <= problem.budget_bytes_per_s * (1 + 1e-9)


@pytest.mark.parametrize("cameras", [3, 30])
def test_a_budget_exactly_at_the_floors_keeps_every_channel_at_its_floor(cameras: int) -> None:
    # Every camera prioritised alike: eq. 4's floors; the budget is what they need on the
    # cheapest rung, to the byte. The priced search (30) and the exhaustive one (3) agree.
    channels = tuple(ChannelSpec(f"/r{i}/camera", 1.0, 16.0, 84_000.0, 0.5) for i in range(cameras))
    ladder = photo_ladder()
    floors = floors_of(Problem(channels, 1.0))
    cheapest = min(r.size_bytes for r in ladder.rungs)
    budget_mbit = float(floors.sum()) * cheapest * 8 / 1e6
    problem = Problem(channels, budget_mbit)
    allocation = allocate_quality(problem, {c.topic: ladder for c in channels})
    assert allocation.status is QualityStatus.OPTIMAL
    assert allocation.size_bytes.tolist() == pytest.approx([cheapest] * cameras)
    assert allocation.rate_hz.tolist() == pytest.approx(floors.tolist(), rel=1e-6)
    assert allocation.total_bytes_per_s <= problem.budget_bytes_per_s * (1 + 1e-9)


# -- per-link capacities ---------------------------------------------------------------------


def with_links(
    rng: np.random.Generator, problem: Problem, ladders: dict[str, Ladder], robots: int
) -> Problem:
    """``problem`` with its cameras dealt to ``robots`` uplinks.

    Each link's capacity is 1.05-2.5 times what its channels' floors need on the cheapest rungs.
    """
    floors = floors_of(problem)
    owner = rng.integers(robots, size=len(problem.topics))
    links = []
    for k in range(robots):
        members = [i for i in range(len(problem.topics)) if owner[i] == k]
        if not members:
            continue
        need = sum(
            floors[i]
            * min(
                r.size_bytes
                for r in allowed(ladders.get(problem.topics[i]), problem.arrays.size_bytes[i])
            )
            for i in members
        )
        cap_bytes = need * float(rng.uniform(1.05, 2.5))
        topics = tuple(problem.topics[i] for i in members)
        links.append(LinkSpec(f"r{k}", cap_bytes * 8 / 1e6, topics))
    return Problem(problem.channels, problem.bandwidth_mbit, links=tuple(links))


def link_spend(problem: Problem, allocation: object) -> dict[str, float]:
    used = np.asarray(allocation.rate_hz) * np.asarray(allocation.size_bytes)  # type: ignore[attr-defined]
    return {
        link.name: float(sum(used[problem.topics.index(t)] for t in link.topics))
        for link in problem.links
    }


@pytest.mark.parametrize(("seed", "n", "robots"), [(0, 4, 2), (1, 6, 3), (2, 8, 2), (3, 10, 4)])
def test_links_within_half_a_percent_of_milp_with_every_link_held(
    seed: int, n: int, robots: int
) -> None:
    rng = np.random.default_rng(seed * 1000 + n)
    problem, ladders = random_instance(rng, n)
    problem = with_links(rng, problem, ladders, robots)
    allocation = allocate_quality(problem, ladders)
    assert allocation.status is QualityStatus.OPTIMAL, allocation.message
    assert allocation.total_bytes_per_s <= problem.budget_bytes_per_s * (1 + 1e-9)
    for link in problem.links:
        assert link_spend(problem, allocation)[link.name] <= link.capacity_mbit * 125_000 * (
            1 + 1e-9
        )
    ours = achieved(problem, ladders, allocation)
    reference = milp_optimum(problem, ladders)
    assert ours >= reference * (1 - GAP), (ours, reference)
    assert allocation.upper_bound is not None
    assert ours <= allocation.upper_bound * (1 + 1e-9)
    assert reference <= allocation.upper_bound * (1 + 1e-6)  # the bound bounds the grid's best


def test_a_tight_uplink_takes_detail_from_its_own_cameras_not_from_the_others() -> None:
    channels = tuple(ChannelSpec(f"/r{k}/camera", 1.0, 16.0, 84_000) for k in (1, 2))
    ladders = {c.topic: photo_ladder() for c in channels}
    free = allocate_quality(Problem(channels, 11.0), ladders)
    capped = allocate_quality(
        Problem(channels, 11.0, links=(LinkSpec("r1", 2.0, ("/r1/camera",)),)), ladders
    )
    assert capped.status is QualityStatus.OPTIMAL
    assert capped.rate_hz[0] * capped.size_bytes[0] <= 2.0 * 125_000 * (1 + 1e-9)
    assert capped.rate_hz[0] * capped.size_bytes[0] < free.rate_hz[0] * free.size_bytes[0]
    # What r1 cannot use goes to r2.
    assert capped.rate_hz[1] * capped.size_bytes[1] > free.rate_hz[1] * free.size_bytes[1]


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31), st.integers(2, 40), st.integers(1, 6))
@example(3484, 2, 3)  # a capped link lowered to the budget's price left a free one over its cap
def test_every_link_and_the_budget_hold_feasible_or_not(seed: int, n: int, robots: int) -> None:
    rng = np.random.default_rng(seed)
    problem, ladders = random_instance(rng, n)
    problem = with_links(rng, problem, ladders, robots)
    if rng.uniform() < 0.3:  # caps and budgets below the floors too: infeasible is a status
        problem = Problem(
            problem.channels,
            problem.bandwidth_mbit * float(rng.uniform(0.2, 1.0)),
            links=tuple(
                LinkSpec(link.name, link.capacity_mbit * float(rng.uniform(0.2, 1.0)), link.topics)
                for link in problem.links
            ),
        )
    allocation = allocate_quality(problem, ladders)
    assert allocation.total_bytes_per_s <= problem.budget_bytes_per_s * (1 + 1e-9)
    spend = link_spend(problem, allocation)
    for link in problem.links:
        assert spend[link.name] <= link.capacity_mbit * 125_000 * (1 + 1e-9), link.name
    if allocation.status is QualityStatus.OPTIMAL:
        assert (allocation.rate_hz >= allocation.floor_hz * (1 - 1e-9)).all()
    assert (allocation.rate_hz <= problem.arrays.max_rate_hz * (1 + 1e-9)).all()


def test_links_that_share_a_channel_are_refused_naming_both() -> None:
    channels = (ChannelSpec("/r1/camera", 1.0, 16.0, 84_000),)
    links = (LinkSpec("up", 5.0, ("/r1/camera",)), LinkSpec("radio", 8.0, ("/r1/camera",)))
    with pytest.raises(SpecError, match="'/r1/camera' crosses links 'up' and 'radio'"):
        allocate_quality(Problem(channels, 11.0, links=links), {"/r1/camera": photo_ladder()})
