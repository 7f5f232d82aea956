"""Rate and quality together: one rung and one rate per channel, under one budget.

Channel ``i`` on rung ``j`` (``dbml.core.ladder``: ``s_ij`` bytes a frame, quality ``Q_ij``) at
rate ``r`` costs ``r s_ij`` bytes/s and is worth::

    u_i(j, r) = w_i * Q_ij ** gamma_i * ln(1 + r / k_i) / ln(1 + fmax_i / k_i)

- ``w_i = WEIGHT_BASE + p'_i``: eq. 2's normalised priority (on the channel's declared size, as
  the paper weighs it), plus a base so that a channel nobody prioritises is still worth a frame;
- the rate's value is concave (a frame adds less the more there are) and 1 at the maximum rate;
- the preference sets ``gamma`` and the rate's knee ``k``: ``keep_rate`` values every frame
  almost as the first (``k`` at the maximum rate: the value is nearly linear), so detail goes
  first; ``keep_detail`` weighs quality steeply (``gamma`` 8) and frames little past the first
  (``k`` 0.25 Hz), so frames go first.

This utility is a modelling assumption, not a human-factors result; the floors are the paper's.
The allocation maximises the sum subject to ``sum_i r_i s_ij <= B``, the paper's priority floor
(eq. 4) ``f'min_i <= r_i <= fmax_i`` and each ladder's quality floor: a multiple-choice knapsack
with a continuous rate. A channel without a ladder is one rung (its declared size, quality 1).

Solver: for a price ``lam`` per byte, each rung's best rate is closed-form,
``r = w Q^gamma / (L lam s) - k`` clipped to its bounds, and each channel takes the rung of
largest ``u - lam * cost`` (the Lagrangian relaxation). Above 64 channels the price is first
sought as a fixed point (choose at a price, fill the choice's rates to the budget, take the
price that needs, again; from the last allocation's price when the caller gives it): where the
choice stays it is exact. Else the price is searched until the choice fits; the rungs are then
fixed and the rates water-filled exactly to the budget (one sort of the rates' breakpoints).
With few channels (at most ``EXACT_COMBINATIONS`` rung combinations) every combination is
water-filled instead and the best kept: exact. The dual value bounds the optimum from above
(``upper_bound``).
Infeasibility is a status: when the floors do not fit on the cheapest rungs, the floors are
pulled back toward the minimums as ``allocate`` does, on the cheapest rungs.

Per-link capacities (a robot's uplink: links that share no channel) are a price per link: a
link whose channels would spend more than its capacity at the budget's price takes its own
allocation at its capacity, alone; the others share what is left (``_solve_links``).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from dbml.core.errors import SpecError
from dbml.core.ladder import PREFERENCE_TERMS, Ladder, Preference
from dbml.core.priority import normalize_priorities
from dbml.core.spec import BYTES_PER_S_PER_MBIT, Problem

__all__ = [
    "EXACT_COMBINATIONS",
    "LOCAL_SEARCH_CHANNELS",
    "PREFERENCE_TERMS",
    "WEIGHT_BASE",
    "QualityAllocation",
    "QualityStatus",
    "allocate_quality",
    "channel_utility",
    "utility",
]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.intp]

WEIGHT_BASE = 0.1
"""What a channel without priority weighs beside a fully prioritised one (1 + 0.1)."""
EXACT_COMBINATIONS = 1024
"""Up to this many rung combinations, every one is tried (exact); beyond, the Lagrangian price."""
LOCAL_SEARCH_CHANNELS = 16
"""Up to this many channels, the price's choice is improved one channel's rung at a time: with
few channels one rung is a large share of the whole, and the price alone may miss by percents."""
_LOCAL_PASSES = 8
_TIGHT_BOUND_CHANNELS = 64
"""Up to this many channels, the duals at the price bracket's ends are computed too: with few
channels the Lagrangian's gap is wider, and two more choices cost little."""
_FIXED_POINT_STEPS = 8
"""Bound on the choose-then-fill rounds tried before the bracketed price search, which starts
from the prices they tried (1-5 rounds settle the bench's fleets of 80-320 cameras)."""
_SETTLING = 2 / 3
"""A round must move at most this share of the channels the one before moved, else the
rounds stop: a choice that settles this slowly is found sooner by the bracket."""
_STEP_OUT = 4.0
"""How far a bracket's missing end is sought from the nearest price tried (a factor)."""
_PRICE_STEPS = 100
"""Bound on the price search's steps (each halves the bracket or closes on its end)."""
_PRICE_REL_TOL = 1e-9
_BUDGET_REL_TOL = 1e-12
_LINK_PASSES = 3
"""Passes that lower a capped link, worth less a byte than the budget's price, to that price."""
_STEP_MIN = 0.1
"""An interpolated price step moves at least this share of the bracket (log scale)."""
_NARROW_LOG_SPAN = 1e-3
"""Below this bracket width (log scale) the price search bisects."""


class QualityStatus(enum.StrEnum):
    """Whether every floor held (``optimal``) or the floors were pulled back (``infeasible``)."""

    OPTIMAL = "optimal"
    INFEASIBLE = "infeasible"


@dataclass(frozen=True, slots=True, eq=False)
class QualityAllocation:
    """A rung and a rate per channel (declaration order), with its status and utility.

    ``rung[i]`` indexes the channel's ladder (-1 for a channel without one); ``size_bytes`` and
    ``quality`` are the chosen rung's. ``upper_bound``: no choice within the budget is worth
    more (the Lagrangian dual's value; the utility itself when every combination was tried;
    None when the status is infeasible).
    """

    status: QualityStatus
    message: str
    budget_bytes_per_s: float
    topics: tuple[str, ...]
    normalized_priority: FloatArray
    floor_hz: FloatArray
    rung: IntArray
    rate_hz: FloatArray
    size_bytes: FloatArray
    quality: FloatArray
    utility: float
    upper_bound: float | None
    price_per_byte: float = math.nan
    """The utility a byte a second is worth at the margin: the Lagrangian price at which the
    rates spend the budget (0: every rate at its maximum fits; NaN: infeasible). The next
    round's ``price_hint``."""

    @property
    def success(self) -> bool:
        """Whether every floor held."""
        return self.status is QualityStatus.OPTIMAL

    @property
    def bytes_per_s(self) -> FloatArray:
        """Each channel's rate times its chosen rung's size."""
        return self.rate_hz * self.size_bytes

    @property
    def total_bytes_per_s(self) -> float:
        """What the channels use together."""
        return float(self.bytes_per_s.sum())


@dataclass(frozen=True, slots=True)
class _Table:
    """The problem as padded arrays: channels x rungs (masked), ready for the price search."""

    size: FloatArray  # (n, m) bytes a frame; +inf where masked
    coef: FloatArray  # (n, m) w Q^gamma / L: u = coef * ln(1 + r / k)
    rung: IntArray  # (n, m) index in the channel's ladder; -1 for a channel without one
    quality: FloatArray  # (n, m)
    valid: npt.NDArray[np.bool_]  # (n, m)
    per_byte: FloatArray  # (n, m) coef / size; 0 where masked
    spend_size: FloatArray  # (n, m) size; 0 where masked
    penalty: FloatArray  # (n, m) 0; -inf where masked
    knee: FloatArray  # (n,) k
    lo: FloatArray  # (n,) floor
    hi: FloatArray  # (n,) fmax
    fmin: FloatArray  # (n,)


def _table(problem: Problem, ladders: Mapping[str, Ladder], floors: FloatArray) -> _Table:
    arrays = problem.arrays
    n = len(problem.topics)
    # Every channel's choices (``Ladder.choice_table``) concatenated: what varies per rung is
    # read from the rows, with no loop per channel but the gathering. A channel without a
    # ladder is one rung of its declared size, quality 1, knee 1 Hz.
    parts = [
        lad.choice_table
        if (lad := ladders.get(topic)) is not None
        else np.array([[arrays.size_bytes[i]], [1.0], [-1.0], [1.0], [1.0], [0.0]])
        for i, topic in enumerate(problem.topics)
    ]
    flat = np.concatenate(parts, axis=1)
    starts = np.flatnonzero(flat[5] == 0)  # each channel's first choice
    counts = np.diff(np.append(starts, flat.shape[1]))
    m = int(counts.max())
    filled = np.arange(m) < counts[:, None]  # row-major: each channel's rungs in order
    size = np.full((n, m), np.inf)
    size[filled] = flat[0]
    quality = np.zeros((n, m))
    quality[filled] = flat[1]
    rung = np.full((n, m), -1, dtype=np.intp)
    rung[filled] = flat[2]
    valued = np.zeros((n, m))
    valued[filled] = flat[3]  # Q ** gamma
    hi = arrays.max_rate_hz
    knee = flat[4][starts]
    knee = np.where(np.isnan(knee), hi, knee)  # nan: the maximum rate
    weight = WEIGHT_BASE + normalize_priorities(arrays.priority, arrays.size_bytes)
    span = np.log1p(hi / knee)
    coef = (weight / span)[:, None] * valued  # 0 where masked
    return _Table(
        size=size,
        coef=coef,
        rung=rung,
        quality=quality,
        valid=filled,
        per_byte=coef / size,  # a masked rung: 0 / inf = 0
        spend_size=np.where(filled, size, 0.0),
        penalty=np.where(filled, 0.0, -np.inf),
        knee=knee,
        lo=floors,
        hi=hi,
        fmin=arrays.min_rate_hz,
    )


def _rates(
    coef: FloatArray,
    size: FloatArray,
    price: float | FloatArray,
    knee: FloatArray,
    *,
    lo: FloatArray,
    hi: FloatArray,
) -> FloatArray:
    """The rate of largest ``u - price * cost`` on rungs of ``coef`` and ``size``: closed form."""
    if np.isscalar(price) and price == 0:  # free: every rate at its maximum
        return np.broadcast_to(hi, np.broadcast_shapes(np.shape(coef), np.shape(hi))).copy()
    # A masked rung has size inf and coef 0: its rate is 0, then clipped; nothing is NaN.
    return np.minimum(np.maximum(coef / (price * size) - knee, lo), hi)  # np.clip costs more


def _choose(
    table: _Table, price: float, rows: IntArray | None = None
) -> tuple[IntArray, FloatArray]:
    """The rung (column) of each channel (of ``rows``) at ``price``, and its rate there."""
    sel = slice(None) if rows is None else rows
    knee = table.knee[sel][:, None]
    # _rates with the division done once in the table: c / (price s) = (c / s) / price.
    rates = np.minimum(
        np.maximum(table.per_byte[sel] * (1.0 / price) - knee, table.lo[sel][:, None]),
        table.hi[sel][:, None],
    )
    value = table.coef[sel] * np.log1p(rates / knee)
    value -= price * table.spend_size[sel] * rates
    value += table.penalty[sel]
    cols = np.argmax(value, axis=1)
    return cols, rates[np.arange(len(cols)), cols]


def _dual(table: _Table, price: float, budget: float) -> tuple[float, IntArray]:
    """The Lagrangian dual at ``price``, and the choice it is made of.

    No choice within the budget is worth more than the dual.
    """
    cols, rates = _choose(table, price)
    rows = np.arange(len(cols))
    size, coef = table.size[rows, cols], table.coef[rows, cols]
    value = price * budget + float(
        (coef * np.log1p(rates / table.knee) - price * size * rates).sum()
    )
    return value, cols


def _picked(table: _Table, cols: IntArray) -> tuple[FloatArray, FloatArray]:
    rows = np.arange(len(cols))
    return table.coef[rows, cols], table.size[rows, cols]


def _water_fill(table: _Table, cols: IntArray, budget: float) -> FloatArray:
    """The best rates for the chosen rungs within ``budget`` (``_fill``'s rates)."""
    return _fill(table, cols, budget)[0]


def _fill(table: _Table, cols: IntArray, budget: float) -> tuple[FloatArray, float]:
    """The best rates for the chosen rungs within ``budget`` (their floors must fit): exact.

    Also the price at which they spend it (0: every rate at its maximum fits).
    """
    coef, size = _picked(table, cols)
    lo, hi, knee = table.lo, table.hi, table.knee
    price = _fill_price(coef, size, lo=lo, hi=hi, knee=knee, budget=budget)
    if price == 0:
        return _free(coef, lo=lo, hi=hi), 0.0
    return _within(table, size, _rates(coef, size, price, knee, lo=lo, hi=hi), budget), price


def _free(coef: FloatArray, *, lo: FloatArray, hi: FloatArray) -> FloatArray:
    """The rates when bytes cost nothing: the maximum, but for a rung worth nothing its floor."""
    return np.where(coef > 0, hi, lo)


def _within(table: _Table, size: FloatArray, rates: FloatArray, budget: float) -> FloatArray:
    """``rates`` with what rounding put above the budget taken from those above their floors."""
    lo, hi = table.lo, table.hi
    over = float(size @ rates) - budget
    if over > 0:
        room_bytes = (rates - lo) * size
        rates = rates - room_bytes / max(float(room_bytes.sum()), 1e-300) * over / size
    return np.clip(rates, lo, hi)


def _best_fill(
    table: _Table, candidates: IntArray, budget: float
) -> tuple[IntArray, FloatArray, float] | None:
    """Of the rung choices ``candidates`` (rows) whose floors fit, the best water-filled.

    Its columns, its exact rates and the price at which they spend the budget; None if no
    candidate's floors fit. Every candidate is filled at once (``_fill_prices``).
    """
    rows = np.arange(candidates.shape[1])
    coef, size = table.coef[rows, candidates], table.size[rows, candidates]
    lo, hi, knee = table.lo, table.hi, table.knee
    fits = size @ lo <= budget * (1 + _BUDGET_REL_TOL)
    if not fits.any():
        return None
    candidates, coef, size = candidates[fits], coef[fits], size[fits]
    price = _fill_prices(coef, size, lo=lo, hi=hi, knee=knee, budget=budget)
    with np.errstate(divide="ignore", invalid="ignore"):  # price 0: bytes are free
        rates = np.where(
            price[:, None] > 0,
            _rates(coef, size, price[:, None], knee, lo=lo, hi=hi),
            _free(coef, lo=lo, hi=hi),
        )
    k = int(np.argmax((coef * np.log1p(rates / knee)).sum(axis=1)))
    return candidates[k], _within(table, size[k], rates[k], budget), float(price[k])


def _fill_price(
    coef: FloatArray,
    size: FloatArray,
    *,
    lo: FloatArray,
    hi: FloatArray,
    knee: FloatArray,
    budget: float,
) -> float:
    """``_fill_prices`` for one choice of rungs, in fewer steps (the price search's inner loop).

    In ``mu = 1 / price`` a channel spends ``clip(c mu - s k, s lo, s hi)``: flat at its floor
    until ``mu = s (lo + k) / c``, then rising at slope ``c`` until ``s (hi + k) / c``, then flat.
    The total is piecewise linear: sorted, the breakpoints give it at every corner, and the
    budget is met on the segment between the two that bracket it.
    """
    floor = float(size @ lo)
    worth = coef > 0
    if worth.all():  # the common case: no rung worth nothing, no copies
        full = float(size @ hi)
        c, sized, low, high, k = coef, size, lo, hi, knee
    else:
        full = float(size @ np.where(worth, hi, lo))
        c, sized, low, high, k = coef[worth], size[worth], lo[worth], hi[worth], knee[worth]
    if full <= budget * (1 + _BUDGET_REL_TOL):
        return 0.0
    per_worth = sized / c
    corners = np.concatenate([per_worth * (low + k), per_worth * (high + k)])
    order = np.argsort(corners, kind="stable")
    mu = corners[order]
    slope = np.cumsum(np.concatenate([c, -c])[order])  # after each corner
    spend = np.empty_like(mu)
    spend[0] = floor
    np.cumsum(slope[:-1] * np.diff(mu), out=spend[1:])
    spend[1:] += floor
    t = int(np.searchsorted(spend, budget, side="left"))  # first corner spending the budget
    if t == 0:  # only rounding: the floors are the budget
        return float(1.0 / mu[0])
    t = min(t, len(mu) - 1)
    mu_star = mu[t - 1] + (budget - spend[t - 1]) / slope[t - 1] if slope[t - 1] > 0 else mu[t]
    return float(1.0 / min(max(mu_star, mu[t - 1]), mu[t]))


def _fill_prices(
    coef: FloatArray,
    size: FloatArray,
    *,
    lo: FloatArray,
    hi: FloatArray,
    knee: FloatArray,
    budget: float,
) -> FloatArray:
    """Per row of rungs (``coef``, ``size``: rows x channels), the price that spends ``budget``.

    ``r_i(lam) = clip(c_i / (lam s_i) - k_i, lo_i, hi_i)`` is continuous and decreasing in the
    price. Sorted by price, each channel's two breakpoints (where it leaves its maximum, where
    it reaches its floor) change the spend ``A / lam + C`` by known amounts: cumulative sums
    give the spend at every breakpoint at once, and the price between the two that bracket the
    budget is ``A / (budget - C)``. 0 where every maximum fits; the floors must fit. A rung worth
    nothing (quality 0) stays at its floor at any price (``_free``).
    """
    worth = coef > 0
    full = (size * _free(coef, lo=lo, hi=hi)).sum(axis=1)
    prices = np.concatenate([coef / (size * (hi + knee)), coef / (size * (lo + knee))], axis=1)
    # Passing its first breakpoint a channel's spend goes from s hi to c / lam - s k; its
    # second, to s lo.
    d_a = np.concatenate([coef, -coef], axis=1)
    d_c = np.concatenate([-size * (hi + knee) * worth, size * (lo + knee) * worth], axis=1)
    order = np.argsort(prices, axis=1, kind="stable")
    prices = np.take_along_axis(prices, order, axis=1)
    a = np.cumsum(np.take_along_axis(d_a, order, axis=1), axis=1)
    c = full[:, None] + np.cumsum(np.take_along_axis(d_c, order, axis=1), axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        spend = np.where(prices > 0, a / prices, 0.0) + c  # at each breakpoint
    # The first breakpoint whose spend is within the budget; the price lies just before it
    # (none within, as rounding may leave floors that just fit: the last, every rate at its floor).
    within = spend <= budget
    t = np.where(within.any(axis=1), np.argmax(within, axis=1), spend.shape[1] - 1)
    rows = np.arange(len(t))
    before = np.maximum(t - 1, 0)
    a_t, c_t = a[rows, before], c[rows, before]
    room = budget - c_t
    with np.errstate(divide="ignore", invalid="ignore"):
        inside = np.where((room > 0) & (a_t > 0), a_t / room, prices[rows, t])
    price = np.minimum(np.maximum(inside, prices[rows, before]), prices[rows, t])
    return np.where(full <= budget * (1 + _BUDGET_REL_TOL), 0.0, price)


def _value(table: _Table, cols: IntArray, rates: FloatArray) -> float:
    coef, _ = _picked(table, cols)
    return float((coef * np.log1p(rates / table.knee)).sum())


def _exact(table: _Table, budget: float) -> tuple[IntArray, FloatArray, float]:
    """Every combination of rungs whose floors fit, filled together; the best and its price."""
    counts = [int(c) for c in table.valid.sum(axis=1)]
    combos = np.array(list(np.ndindex(*counts)), dtype=np.intp)  # (K, n)
    found = _best_fill(table, combos, budget)
    if found is None:  # not expected: the caller checked the cheapest rungs' floors
        raise AssertionError("no rung combination fits its floors")
    return found


def _improve(
    table: _Table, cols: IntArray, rates: FloatArray, budget: float
) -> tuple[IntArray, FloatArray]:
    """Change one channel's rung at a time (rates water-filled again) while it gains."""
    best = _value(table, cols, rates)
    for _ in range(_LOCAL_PASSES):
        improved = False
        for i in range(len(cols)):
            for col in np.flatnonzero(table.valid[i]):
                if col == cols[i]:
                    continue
                trial = cols.copy()
                trial[i] = col
                if float(_picked(table, trial)[1] @ table.lo) > budget * (1 + _BUDGET_REL_TOL):
                    continue
                trial_rates = _water_fill(table, trial, budget)
                gain = _value(table, trial, trial_rates)
                if gain > best * (1 + 1e-12):
                    best, cols, rates, improved = gain, trial, trial_rates, True
        if not improved:
            break
    return cols, rates


def _priced(
    table: _Table, budget: float, hint: float | None = None
) -> tuple[IntArray, FloatArray, float, float]:
    """The Lagrangian price search; the exact rates for its rungs, the bound and the price.

    ``hint``: a price to start from (the last round's). Only the channels whose rung differs at
    the bracket's two ends are chosen again at each step; the others keep their rung and only
    their rate follows the price.
    """
    # Free: every rate at its maximum, so each channel's best rung is its most valuable.
    cols = np.argmax(np.where(table.valid, table.coef, -np.inf), axis=1)
    size = _picked(table, cols)[1]
    if float(size @ table.hi) <= budget:
        return cols, table.hi.copy(), _value(table, cols, table.hi), 0.0
    finite = table.valid & (table.coef > 0)
    if not finite.any():  # nothing is worth anything: every channel at its floor, cheapest rung
        return np.argmin(table.size, axis=1), table.lo.copy(), 0.0, 0.0
    ends: list[tuple[float, IntArray, float]] = []
    if len(table.lo) > _TIGHT_BOUND_CHANNELS:
        settled = _fixed_point(table, budget, ends, hint)
        if settled is not None:
            return settled
    # The bracket: the tightest of the fixed point's prices on each side (a side it never
    # reached: stepped out from the nearest price tried), else a wide one.
    over = [end for end in ends if end[2] > budget]
    within = [end for end in ends if end[2] <= budget]
    per_byte = table.coef / np.where(finite, table.size, 1.0)
    widest_low = float((per_byte / (table.hi + table.knee)[:, None])[finite].min()) / 2
    widest_high = float((per_byte / (table.lo + table.knee)[:, None])[finite].max()) * 2
    if over:
        low, cols_low, spend_low = max(over, key=lambda end: end[0])
    else:
        low = max(min((end[0] for end in within), default=widest_low) / _STEP_OUT, widest_low)
        for _ in range(_PRICE_STEPS):  # a price low enough that the choice overspends
            cols_low, rates_low = _choose(table, low)
            spend_low = float(_picked(table, cols_low)[1] @ rates_low)
            if spend_low > budget or low <= widest_low:
                break
            low = max(low / _STEP_OUT, widest_low)
    if within:
        high, cols_high, spend_high = min(within, key=lambda end: end[0])
    else:
        high = low * _STEP_OUT if over else max(widest_high, low * 4)
        cols_high, rates_high = _choose(table, high)
        spend_high = float(_picked(table, cols_high)[1] @ rates_high)
    for _ in range(_PRICE_STEPS):  # the cheapest rungs win at a price high enough
        if spend_high <= budget:
            break
        low, high, cols_low, spend_low = high, high * 16, cols_high, spend_high
        cols_high, rates_high = _choose(table, high)
        spend_high = float(_picked(table, cols_high)[1] @ rates_high)
    lo, hi, kn = table.lo, table.hi, table.knee
    side = 0  # which end the last two steps moved (Illinois: halve the other's pull)
    pull_low = pull_high = 1.0
    for _ in range(_PRICE_STEPS):
        undecided = np.flatnonzero(cols_low != cols_high)
        if len(undecided) <= 1 or high <= low * (1 + _PRICE_REL_TOL):
            break  # one channel's rung at most is in doubt: the feasible end's is taken
        mid = _interpolate((low, high), (spend_low, spend_high), budget, (pull_low, pull_high))
        cols_mid = cols_high.copy()
        cols_mid[undecided] = _choose(table, mid, undecided)[0]
        c, s = _picked(table, cols_mid)
        spend = float(s @ _rates(c, s, mid, kn, lo=lo, hi=hi))
        if spend > budget:
            low, cols_low, spend_low = mid, cols_mid, spend
            pull_high, pull_low = (pull_high / 2, 1.0) if side == -1 else (1.0, 1.0)
            side = -1
        else:
            high, cols_high, spend_high = mid, cols_mid, spend
            pull_low, pull_high = (pull_low / 2, 1.0) if side == 1 else (1.0, 1.0)
            side = 1
    few = len(cols_high) <= _TIGHT_BOUND_CHANNELS
    bound = math.inf
    if few:  # cheap here: each end's exact choice, and the tighter of their duals
        bound_high, cols_high = _dual(table, high, budget)
        bound_low, cols_low = _dual(table, low, budget)
        bound = min(bound_low, bound_high)
    # The bracket's two ends differ in one channel's rung at most: each, water-filled; the best.
    found = _best_fill(table, np.stack([cols_high, cols_low]), budget)
    if found is None:  # not expected: the high end's choice fits at its price
        cols = np.argmin(table.size, axis=1)
        rates, price = _fill(table, cols, budget)
        return cols, rates, _dual(table, high, budget)[0], price
    cols, rates, price = found
    if not few:
        # The dual at the price that spends the budget bounds the optimum tightly; its own
        # choice (exact at that price) is one more candidate.
        bound, exact = _dual(table, price if price > 0 else high, budget)
        if (exact != cols).any():
            found = _best_fill(table, np.stack([cols, exact]), budget)
            assert found is not None  # cols fit
            cols, rates, price = found
    return cols, rates, bound, price


def _fixed_point(
    table: _Table,
    budget: float,
    ends: list[tuple[float, IntArray, float]],
    hint: float | None = None,
) -> tuple[IntArray, FloatArray, float, float] | None:
    """The rungs chosen at the very price at which their own rates spend the budget: exact.

    From the rungs chosen at ``hint`` (the last round's price: one round when little moved),
    else the most valuable rungs (or the cheapest, if those floors do not fit): fill their
    rates to the budget, choose every channel's rung at the price that takes, and again, until
    the choice stays. There the rates are each rung's best
    at that price and spend the budget whole, so the Lagrangian's bound is met: nothing within
    the budget is worth more. Where one channel's rung flips back and forth (the relaxation's
    gap), the better of its two fills, bounded by the dual at that price. None when the choice
    settles slowly (``_SETTLING``) or a choice's floors do not fit; the bracketed search follows,
    from the prices tried: each with its choice and what that spends is added to ``ends``.
    """
    lo, hi, knee = table.lo, table.hi, table.knee
    # From the most valuable rungs (the caller found they do not fit at their maximum rates,
    # so they spend the budget at a positive price), or the cheapest if their floors do not fit.
    cols = np.argmax(np.where(table.valid, table.coef, -np.inf), axis=1)
    if hint is not None and math.isfinite(hint) and hint > 0:
        cols = _choose(table, hint)[0]
    if float(_picked(table, cols)[1] @ lo) > budget * (1 + _BUDGET_REL_TOL):
        cols = np.argmin(table.size, axis=1)
    moved = len(cols)  # how many channels the last round moved to another rung
    for _ in range(_FIXED_POINT_STEPS):
        coef, size = _picked(table, cols)
        if float(size @ lo) > budget * (1 + _BUDGET_REL_TOL):
            return None
        price = _fill_price(coef, size, lo=lo, hi=hi, knee=knee, budget=budget)
        if price == 0:
            return None  # every rate at its maximum fits: the caller's free case
        chosen, rates = _choose(table, price)
        chosen_size = _picked(table, chosen)[1]
        ends.append((price, chosen, float(chosen_size @ rates)))
        if np.array_equal(chosen, cols):
            value = float((coef * np.log1p(rates / knee)).sum())
            spend = float(size @ rates)
            bound = value + price * (budget - spend)  # the dual at this price
            return cols, _within(table, size, rates, budget), max(bound, value), price
        changed = int(np.count_nonzero(chosen != cols))
        if changed == moved == 1:  # one channel's rung in doubt, twice: each way, the better
            found = _best_fill(table, np.stack([cols, chosen]), budget)
            if found is None:
                return None
            return found[0], found[1], _dual(table, price, budget)[0], found[2]
        if changed > moved * _SETTLING:
            return None  # not settling (or a cycle): the bracket's ends are in ``ends``
        cols, moved = chosen, changed
    return None


def _interpolate(
    ends: tuple[float, float],
    spends: tuple[float, float],
    budget: float,
    pulls: tuple[float, float],
) -> float:
    """The next price: where the spend meets the budget, interpolated in log-log (Illinois).

    The spend falls roughly as a power of the price, so the interpolation lands near the
    answer; a pull halved each time the same end moves twice keeps it from stalling, and a
    step that would not shrink the bracket by a tenth is the geometric midpoint instead.
    """
    (low, high), (spend_low, spend_high), (pull_low, pull_high) = ends, spends, pulls
    span = math.log(high / low)
    a = math.log(max(spend_low, 1e-300) / budget) * pull_low
    b = math.log(budget / max(spend_high, 1e-300)) * pull_high
    t = a / (a + b) if a + b > 0 else 0.5
    t = min(max(t, _STEP_MIN), 1 - _STEP_MIN) if span > _NARROW_LOG_SPAN else 0.5
    return low * math.exp(span * t)


def channel_utility(
    *,
    weight: float,
    quality: float,
    rate_hz: float,
    max_rate_hz: float,
    preference: Preference = Preference.BALANCED,
) -> float:
    """One channel's utility (the module docstring's ``u_i``): how a run is judged afterwards.

    ``weight`` is ``WEIGHT_BASE`` plus eq. 2's normalised priority; ``quality`` the score of
    what was seen (a measured SSIM), ``rate_hz`` what was delivered.
    """
    gamma, knee = PREFERENCE_TERMS[Preference(preference)]
    k = max_rate_hz if knee is None else knee
    value = math.log1p(max(rate_hz, 0.0) / k) / math.log1p(max_rate_hz / k)
    return float(weight * max(quality, 0.0) ** gamma * value)


def utility(
    problem: Problem, ladders: Mapping[str, Ladder], rung: IntArray, rate_hz: FloatArray
) -> float:
    """The utility (module docstring) of ``rung`` (ladder indices, -1: none) at ``rate_hz``."""
    floors = problem.arrays.min_rate_hz
    table = _table(problem, ladders, floors)
    cols = np.empty(len(rung), dtype=np.intp)
    for i, j in enumerate(rung):
        hits = np.flatnonzero(table.rung[i] == j) if j >= 0 else np.array([0])
        if len(hits) == 0:
            raise SpecError(f"channel {problem.topics[i]!r}: rung={int(j)} is not allowed")
        cols[i] = hits[0]
    return _value(table, cols, np.asarray(rate_hz, dtype=float))


def allocate_quality(
    problem: Problem, ladders: Mapping[str, Ladder], *, price_hint: float | None = None
) -> QualityAllocation:
    """A rung and a rate for every channel (see the module docstring); infeasible is a status.

    ``ladders`` by topic; a topic not in the problem is an error, a channel without a ladder
    keeps its declared size. Per-link capacities (``problem.links``, each its capacity times
    the utilisation) hold too, for links that share no channel (``SpecError`` otherwise).
    ``price_hint``: the last allocation's ``price_per_byte``, where a large fleet's search
    starts (the answer does not depend on it, only how soon it is found).
    """
    unknown = sorted(set(ladders) - set(problem.topics))
    if unknown:
        raise SpecError(f"ladder of topic {unknown[0]!r}: no such channel in the problem")
    arrays = problem.arrays
    budget = problem.budget_bytes_per_s
    normalized = normalize_priorities(arrays.priority, arrays.size_bytes)
    fmin, fmax = arrays.min_rate_hz, arrays.max_rate_hz
    floors = (fmax - fmin) * normalized + fmin
    table = _table(problem, ladders, floors)
    if problem.links:
        solved = _solve_links(problem, table, budget, price_hint)
    else:
        solved = _solve(table, budget, price_hint)
    cols, rates = solved.cols, solved.rates
    rows = np.arange(len(problem.topics))
    chosen_size = table.size[rows, cols]
    used = float(chosen_size @ rates)
    value = _value(table, cols, rates)
    message, upper = solved.message, solved.upper
    if solved.status is QualityStatus.OPTIMAL:
        message = (
            f"{used / BYTES_PER_S_PER_MBIT:.3f} Mbit/s of a "
            f"{budget / BYTES_PER_S_PER_MBIT:.3f} Mbit/s budget allocated"
        )
        upper = value if upper is None else max(upper, value)
    return QualityAllocation(
        status=solved.status,
        message=message,
        budget_bytes_per_s=budget,
        topics=problem.topics,
        normalized_priority=_frozen(normalized),
        floor_hz=_frozen(floors),
        rung=_frozen_int(table.rung[rows, cols]),
        rate_hz=_frozen(np.asarray(rates, dtype=float)),
        size_bytes=_frozen(chosen_size),
        quality=_frozen(table.quality[rows, cols]),
        utility=value,
        upper_bound=upper,
        price_per_byte=solved.price,
    )


@dataclass(frozen=True, slots=True)
class _Solved:
    """A table's rungs and rates within one budget, before they become an allocation."""

    status: QualityStatus
    message: str  # why, when infeasible
    cols: IntArray
    rates: FloatArray
    upper: float | None  # no choice within the budget is worth more (None: unknown)
    price: float  # the Lagrangian price the rates spend the budget at (NaN: infeasible)


def _solve(table: _Table, budget: float, price_hint: float | None = None) -> _Solved:
    """The best rungs and rates of ``table`` within ``budget``.

    Floors that do not fit on the cheapest rungs are pulled back (infeasible, a status).
    """
    fmin, floors = table.fmin, table.lo
    rows = np.arange(len(floors))
    cheapest = np.argmin(table.size, axis=1)
    cheap_size = table.size[rows, cheapest]
    need = float(cheap_size @ floors)
    if need > budget * (1 + _BUDGET_REL_TOL):
        need_min = float(cheap_size @ fmin)
        if need_min > budget:
            fraction = budget / need_min
            rates = fraction * fmin
            message = (
                f"minimum rates need {need_min / BYTES_PER_S_PER_MBIT:.3f} Mbit/s on the cheapest "
                f"rungs but the budget allows {budget / BYTES_PER_S_PER_MBIT:.3f} Mbit/s; every "
                f"channel runs at {fraction:.1%} of its minimum"
            )
        else:
            alpha = (budget - need_min) / (need - need_min)
            rates = fmin + alpha * (floors - fmin)
            message = (
                f"priority floors need {need / BYTES_PER_S_PER_MBIT:.3f} Mbit/s on the cheapest "
                f"rungs but the budget allows {budget / BYTES_PER_S_PER_MBIT:.3f} Mbit/s; floors "
                f"pulled back to {alpha:.1%} of their height above the minimum rates"
            )
        return _Solved(QualityStatus.INFEASIBLE, message, cheapest, rates, None, math.nan)
    upper = None
    if float(np.log(table.valid.sum(axis=1)).sum()) <= math.log(EXACT_COMBINATIONS) + 1e-9:
        cols, rates, price = _exact(table, budget)  # every combination: value is the bound
    else:
        cols, rates, upper, price = _priced(table, budget, price_hint)
        if len(cols) <= LOCAL_SEARCH_CHANNELS:
            cols, rates = _improve(table, cols, rates, budget)
            price = _fill(table, cols, budget)[1]
    return _Solved(QualityStatus.OPTIMAL, "", cols, rates, upper, price)


def _solve_links(
    problem: Problem, table: _Table, budget: float, price_hint: float | None
) -> _Solved:
    """``_solve`` within the budget and every link's capacity (links that share no channel).

    At the budget's price ``lam`` a link whose channels would spend more than its capacity pays
    its own higher price ``pi``, the one at which they spend the capacity alone; so a link is
    either capped (``pi >= lam``: its channels take its own allocation, the whole capacity) or
    free (its channels follow ``lam`` and stay within it). From every link free: the channels
    of the free links are solved within what the capped ones leave, and every free link that
    went over is capped (solved alone, once). Capping only lowers ``lam``, so a capped link
    stays above it; where a rung's step leaves one below, it is freed (lowest ``pi`` first) and
    capped for good if it goes over again. The bound is the sum of the parts' duals at their
    own prices.
    """
    n, count = len(problem.topics), len(problem.links)
    index = {topic: i for i, topic in enumerate(problem.topics)}
    member = np.full(n, -1, dtype=np.intp)
    for k, link in enumerate(problem.links):
        for topic in link.topics:
            i = index[topic]
            if member[i] >= 0:
                raise SpecError(
                    f"channel {topic!r} crosses links {problem.links[member[i]].name!r} and "
                    f"{link.name!r}: the quality allocation takes links that share no channel"
                )
            member[i] = k
    caps = np.array([link.capacity_mbit for link in problem.links])
    caps *= BYTES_PER_S_PER_MBIT * problem.utilization
    groups = [np.flatnonzero(member == k) for k in range(count)]
    crossing = member >= 0
    alone: dict[int, _Solved] = {}  # each capped link's own allocation at its capacity

    def capped_price(k: int) -> float:  # infeasible alone: capped whatever the budget's price
        solved = alone[k]
        return math.inf if solved.status is QualityStatus.INFEASIBLE else solved.price

    capped = np.zeros(count, dtype=bool)
    pinned = np.zeros(count, dtype=bool)
    # Each round caps a link or frees one; a freed link is capped again at most once, for good.
    for _ in range(3 * count + 2):
        free = np.flatnonzero(~(crossing & capped[np.maximum(member, 0)]))
        left = budget - sum(
            (_spend(table, groups[k], alone[k]) for k in np.flatnonzero(capped).tolist()), 0.0
        )
        if len(free):
            rest = _solve(_rows(table, free), max(left, 0.0), price_hint)
        else:  # every link capped: within the budget, or one must follow its price after all
            rest = _Solved(QualityStatus.OPTIMAL, "", free, np.zeros(0), 0.0, 0.0)
            if left < 0:
                rest = _Solved(QualityStatus.INFEASIBLE, "", free, np.zeros(0), None, math.nan)
        price = rest.price if rest.status is QualityStatus.OPTIMAL else math.inf
        spent = np.zeros(n)
        spent[free] = table.spend_size[free, rest.cols] * rest.rates
        by_link = np.bincount(member[crossing], weights=spent[crossing], minlength=count)
        over = np.flatnonzero(~capped & (by_link > caps * (1 + 1e-9)))
        if len(over):  # solved alone at its capacity; capped (for good if it was freed)
            for k in over.tolist():
                if k not in alone:
                    alone[k] = _solve(_rows(table, groups[k]), float(caps[k]))
                else:
                    pinned[k] = True
            capped[over] = True
            continue
        cheaper = sorted((capped_price(k), k) for k in np.flatnonzero(capped & ~pinned).tolist())
        if not cheaper or cheaper[0][0] >= price:
            break
        capped[cheaper[0][1]] = False
    else:  # pragma: no cover - bounded by the count above
        raise AssertionError("the links' caps did not settle")
    # A link capped for good (its choice at the budget's price jumps over its capacity) may be
    # worth less a byte at its capacity than the budget's price: its rungs then run at their
    # rates at that price, within the capacity, and what that leaves goes to the free channels.
    for _ in range(_LINK_PASSES):
        price = rest.price if rest.status is QualityStatus.OPTIMAL else math.inf
        before = (dict(alone), rest)
        lowered = False
        for k in np.flatnonzero(capped).tolist():
            solved = alone[k]
            if not 0 < capped_price(k) < price < math.inf:
                continue
            group = groups[k]
            coef, size = table.coef[group, solved.cols], table.size[group, solved.cols]
            at_price = _rates(
                coef, size, price, table.knee[group], lo=table.lo[group], hi=table.hi[group]
            )
            spend = float(size @ at_price)
            if spend < _spend(table, group, solved) * (1 - 1e-9):
                alone[k] = _solve(_rows(table, group), spend)
                lowered = True
        if not lowered or not len(free):
            break
        left = budget - sum(
            (_spend(table, groups[k], alone[k]) for k in np.flatnonzero(capped).tolist()), 0.0
        )
        rest = _solve(_rows(table, free), max(left, 0.0), price_hint)
        spent = np.zeros(n)
        spent[free] = table.spend_size[free, rest.cols] * rest.rates
        by_link = np.bincount(member[crossing], weights=spent[crossing], minlength=count)
        if np.any(~capped & (by_link > caps * (1 + 1e-9))):
            # What the lowered links left took a free link over its capacity: the pass before
            # held every link.
            alone, rest = before
            break
    cols = np.zeros(n, dtype=np.intp)
    rates = np.zeros(n)
    cols[free], rates[free] = rest.cols, rest.rates
    status, messages = rest.status, [rest.message] if rest.message else []
    for k in np.flatnonzero(capped).tolist():
        cols[groups[k]], rates[groups[k]] = alone[k].cols, alone[k].rates
        if alone[k].status is QualityStatus.INFEASIBLE:
            status = QualityStatus.INFEASIBLE
            messages.append(f"link {problem.links[k].name!r}: {alone[k].message}")
    if status is QualityStatus.INFEASIBLE:
        total = float(table.spend_size[np.arange(n), cols] @ rates)
        if total > budget:  # links' floors pulled back within each, the budget still holds
            rates = rates * (budget / total)
        if not messages:
            messages.append("the links' pulled-back floors need more than the budget")
        return _Solved(status, "; ".join(messages), cols, rates, None, math.nan)
    # Lagrangian bound: the free part's dual at its price, each capped link's at its own.
    parts = [(free, rest, budget - float(caps[capped].sum()))]
    parts += [(groups[k], alone[k], float(caps[k])) for k in np.flatnonzero(capped).tolist()]
    bound = 0.0
    for part, solved, part_budget in parts:
        if not len(part):
            continue
        sub = _rows(table, part)
        if solved.price > 0:
            bound += _dual(sub, solved.price, part_budget)[0]
        else:  # bytes free: every rate at its maximum on its best rung, the part's optimum
            bound += _value(sub, solved.cols, solved.rates)
    value = _value(table, cols, rates)
    return _Solved(status, "", cols, rates, max(bound, value), rest.price)


def _rows(table: _Table, rows: IntArray) -> _Table:
    """The table of the channels ``rows`` alone."""
    return _Table(**{name: getattr(table, name)[rows] for name in _Table.__slots__})


def _spend(table: _Table, group: IntArray, solved: _Solved) -> float:
    """The bytes a second ``solved`` (of the channels ``group``) spends."""
    return float(table.spend_size[group, solved.cols] @ solved.rates)


def _frozen(array: FloatArray) -> FloatArray:
    out = np.array(array, dtype=float)
    out.flags.writeable = False
    return out


def _frozen_int(array: IntArray) -> IntArray:
    out = np.array(array, dtype=np.intp)
    out.flags.writeable = False
    return out
