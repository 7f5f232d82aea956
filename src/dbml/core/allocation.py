"""Allocation strategies: from a problem to a publish rate per channel.

The paper's problem (eq. 2-5), for channels ``i`` with message size ``w_i`` (bytes), bounds
``fmin_i <= fmax_i`` (Hz), raw priority ``p_i`` and a budget ``B`` (bytes/s)::

    p'_i      = p_i w_i / sum_k p_k w_k                       (eq. 2, all 0 if the sum is 0)
    f'min_i   = (fmax_i - fmin_i) p'_i + fmin_i               (eq. 4, the priority floor)
    maximise    sum_i w_i f_i
    subject to  sum_i w_i f_i <= B,   f'min_i <= f_i <= fmax_i (eq. 5)

Every allocation that fills ``B`` is optimal, so the LP alone leaves the rates arbitrary. dbml
breaks the tie deterministically: among optimal allocations, the one with the largest total
message rate, and among those the one favouring channels declared earlier. Equivalently: raise
every channel to its floor, then hand the remaining budget to channels in ascending message size
(ties in declaration order), each up to its maximum. This reproduces every row of the paper's
Table 2.

Infeasibility is a result, not an exception: when the floors do not fit, they are pulled back
toward ``fmin`` by one common factor; when even the minimums do not fit, every channel runs at the
same fraction of its minimum. The rates always respect the budget (and, for ``lp``, every link).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.optimize import linprog

from dbml.core.errors import DbmlError, SpecError
from dbml.core.priority import normalize_priorities
from dbml.core.spec import BYTES_PER_S_PER_MBIT, Problem

__all__ = ["Allocation", "ChannelAllocation", "Status", "Strategy", "allocate"]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

_REL_TOL = 1e-12
"""Relative slack when comparing sums of floats with a capacity."""
_LP_TIE_WEIGHT = 1e-6
"""Stage-two weight by which ``lp`` prefers earlier channels among otherwise equal allocations."""


class Strategy(enum.StrEnum):
    """How the budget is shared; see ``allocate``."""

    PAPER = "paper"
    STATIC = "static"
    FAIR = "fair"
    LP = "lp"


class Status(enum.StrEnum):
    """Whether the budget held every floor (``optimal``) or the floors were pulled back."""

    OPTIMAL = "optimal"
    INFEASIBLE = "infeasible"


@dataclass(frozen=True, slots=True)
class ChannelAllocation:
    """One channel's row of an allocation; ``share`` is of the link's full bandwidth."""

    topic: str
    priority: float
    normalized_priority: float
    floor_hz: float
    rate_hz: float
    bytes_per_s: float
    share: float


def _frozen(array: FloatArray) -> FloatArray:
    array.flags.writeable = False
    return array


@dataclass(frozen=True, slots=True, eq=False)
class Allocation:
    """The result of ``allocate``: a status, a message and one rate per channel.

    Column arrays (read-only, declaration order) keep large fleets cheap; ``channels`` gives the
    same data row by row.
    """

    strategy: Strategy
    status: Status
    message: str
    budget_bytes_per_s: float
    link_bytes_per_s: float
    topics: tuple[str, ...]
    priority: FloatArray
    normalized_priority: FloatArray
    floor_hz: FloatArray
    rate_hz: FloatArray
    size_bytes: FloatArray

    @property
    def success(self) -> bool:
        """Whether the allocation is optimal."""
        return self.status is Status.OPTIMAL

    @property
    def bytes_per_s(self) -> FloatArray:
        """Each channel's rate times its size."""
        return self.rate_hz * self.size_bytes

    @property
    def total_bytes_per_s(self) -> float:
        """What the channels use together."""
        return float(self.bytes_per_s.sum())

    @property
    def channels(self) -> tuple[ChannelAllocation, ...]:
        """One row per channel, in declaration order."""
        used = self.bytes_per_s
        return tuple(
            ChannelAllocation(
                topic=topic,
                priority=float(self.priority[i]),
                normalized_priority=float(self.normalized_priority[i]),
                floor_hz=float(self.floor_hz[i]),
                rate_hz=float(self.rate_hz[i]),
                bytes_per_s=float(used[i]),
                share=float(used[i] / self.link_bytes_per_s),
            )
            for i, topic in enumerate(self.topics)
        )

    def rates_by_topic(self) -> dict[str, float]:
        """The rates as plain floats by topic."""
        return dict(zip(self.topics, (float(r) for r in self.rate_hz), strict=True))


@dataclass(frozen=True, slots=True)
class _Row:
    """A capacity constraint ``sum_{i in mask} w_i f_i <= cap`` (the budget, or one link)."""

    label: str
    mask: BoolArray | None  # None: every channel (the budget), without the cost of a mask
    cap_bytes_per_s: float

    def used(self, w: FloatArray, rates: FloatArray) -> float:
        if self.mask is None:
            return float(w @ rates)
        return float(w[self.mask] @ rates[self.mask])


def _mbit(bytes_per_s: float) -> str:
    return f"{bytes_per_s / BYTES_PER_S_PER_MBIT:.3f} Mbit/s"


def _relax(
    w: FloatArray, fmin: FloatArray, floors: FloatArray, rows: list[_Row], floor_name: str
) -> tuple[FloatArray, str | None, bool]:
    """Lower bounds that fit every row: the floors, pulled back toward ``fmin`` if needed.

    Returns the bounds, the infeasibility message (None if the floors fit) and whether even the
    minimums had to be scaled down (then the bounds are the final rates).
    """
    need_floor = [r.used(w, floors) for r in rows]
    if all(
        need <= r.cap_bytes_per_s * (1 + _REL_TOL) for need, r in zip(need_floor, rows, strict=True)
    ):
        return floors, None, False
    need_min = [r.used(w, fmin) for r in rows]
    short = [i for i, r in enumerate(rows) if need_min[i] > r.cap_bytes_per_s * (1 + _REL_TOL)]
    if short:
        fractions = [rows[i].cap_bytes_per_s / need_min[i] for i in short]
        worst = short[int(np.argmin(fractions))]
        beta = min(fractions)
        message = (
            f"minimum rates need {_mbit(need_min[worst])} but {rows[worst].label} allows "
            f"{_mbit(rows[worst].cap_bytes_per_s)}; every channel runs at {beta:.1%} of its minimum"
        )
        return beta * fmin, message, True
    over = [i for i, r in enumerate(rows) if need_floor[i] > r.cap_bytes_per_s * (1 + _REL_TOL)]
    alphas = [(rows[i].cap_bytes_per_s - need_min[i]) / (need_floor[i] - need_min[i]) for i in over]
    worst = over[int(np.argmin(alphas))]
    alpha = min(1.0, max(0.0, min(alphas)))
    message = (
        f"{floor_name} need {_mbit(need_floor[worst])} but {rows[worst].label} allows "
        f"{_mbit(rows[worst].cap_bytes_per_s)}; floors pulled back to {alpha:.1%} of their "
        f"height above the minimum rates"
    )
    return fmin + alpha * (floors - fmin), message, False


def _fill_ascending_size(
    w: FloatArray,
    lower: FloatArray,
    upper: FloatArray,
    budget: float,
    order: npt.NDArray[np.intp],
) -> FloatArray:
    """Raise channels from ``lower`` toward ``upper`` in ``order`` until ``budget`` is used."""
    rates = lower.copy()
    remaining = budget - float(w @ lower)
    if remaining <= 0.0:
        return rates
    cumulative = np.cumsum((w * (upper - lower))[order])
    if cumulative[-1] <= remaining:
        return upper.copy()
    full = int(np.searchsorted(cumulative, remaining, side="right"))
    raised = order[:full]
    rates[raised] = upper[raised]
    i = order[full]
    left = remaining - (float(cumulative[full - 1]) if full else 0.0)
    rates[i] = min(upper[i], lower[i] + max(0.0, left) / w[i])
    return rates


def _water_level(w: FloatArray, lower: FloatArray, upper: FloatArray, budget: float) -> float:
    """The largest level ``L`` with ``sum w * clip(L, lower, upper) <= budget``.

    Assumes ``sum w * lower <= budget``. Bisection brackets the segment of the piecewise-linear
    total that holds ``L``; one linear solve on that segment then gives it exactly.
    """

    def total(level: float) -> float:
        return float(w @ np.clip(level, lower, upper))

    top = float(upper.max())
    if total(top) <= budget:
        return top
    low, high = float(lower.min()), top
    for _ in range(200):
        mid = 0.5 * (low + high)
        if mid in (low, high):
            break
        if total(mid) <= budget:
            low = mid
        else:
            high = mid
    sliding = (lower <= low) & (upper >= high)
    fixed = float(w[~sliding] @ np.clip(low, lower[~sliding], upper[~sliding]))
    weight = float(w[sliding].sum())
    if weight > 0.0:
        exact = (budget - fixed) / weight
        if low <= exact <= high and total(exact) <= budget * (1 + _REL_TOL):
            return exact
    return low


def _enforce_rows(
    w: FloatArray, lower: FloatArray, rates: FloatArray, rows: list[_Row]
) -> FloatArray:
    """Scale back what a solver's tolerance put above a row's capacity (never below ``lower``)."""
    rates = rates.copy()
    for row in rows:
        used = row.used(w, rates)
        if used <= row.cap_bytes_per_s:
            continue
        base = row.used(w, lower)
        extra = used - base
        scale = max(0.0, (row.cap_bytes_per_s - base) / extra) if extra > 0 else 0.0
        members = slice(None) if row.mask is None else row.mask
        rates[members] = lower[members] + (rates[members] - lower[members]) * scale
    return rates


def _solve_lp(w: FloatArray, lower: FloatArray, upper: FloatArray, rows: list[_Row]) -> FloatArray:
    """Two HiGHS solves: the most bytes, then the most messages among those (earlier first)."""
    n = len(w)
    a_ub = np.stack([w if r.mask is None else np.where(r.mask, w, 0.0) for r in rows])
    b_ub = np.array([r.cap_bytes_per_s for r in rows])
    bounds = list(zip(lower.tolist(), upper.tolist(), strict=True))
    first = linprog(-w, A_ub=a_ub, b_ub=b_ub, bounds=bounds, method="highs")
    if first.status != 0 or first.x is None:
        # The lower bounds were relaxed to fit every row, so this is numerical trouble, not input.
        raise DbmlError(f"lp: HiGHS failed on a feasible problem: {first.message}")
    best = float(w @ first.x)
    preference = 1.0 + _LP_TIE_WEIGHT * (n - np.arange(n)) / n
    second = linprog(
        -preference,
        A_ub=np.vstack([a_ub, -w[None, :]]),
        b_ub=np.append(b_ub, -best * (1 - 1e-9)),
        bounds=bounds,
        method="highs",
    )
    rates = np.asarray(second.x if second.status == 0 else first.x, dtype=float)
    return _enforce_rows(w, lower, np.clip(rates, lower, upper), rows)


def _rows(problem: Problem, strategy: Strategy) -> list[_Row]:
    rows = [_Row("the budget", None, problem.budget_bytes_per_s)]
    if not problem.links:
        return rows
    if strategy is not Strategy.LP:
        raise SpecError(
            f"strategy={strategy.value!r} does not support links "
            f"(link {problem.links[0].name!r}); use strategy 'lp'"
        )
    index = {topic: i for i, topic in enumerate(problem.topics)}
    for link in problem.links:
        mask = np.zeros(len(problem.topics), dtype=bool)
        mask[[index[t] for t in link.topics]] = True
        cap = link.capacity_mbit * BYTES_PER_S_PER_MBIT * problem.utilization
        rows.append(_Row(f"link {link.name!r}", mask, cap))
    return rows


def allocate(problem: Problem, *, strategy: Strategy | str = Strategy.PAPER) -> Allocation:
    """Share the problem's budget among its channels; infeasibility is a status, not an error.

    Strategies (floors are eq. 4's ``f'min`` except for ``static``):

    - ``paper``: eq. 2-5 with the tie-break of this module's docstring; exact, O(n log n).
    - ``static``: the paper's baseline, one common rate ``B / sum w`` for every channel, each
      clipped to its bounds (lowered until it fits if minimums push the total over ``B``).
    - ``fair``: the paper's proposed modification (section 4.3): above the priority floors, raise
      the lowest rates first (water-filling on frequency), so equal priorities get equal rates.
    - ``lp``: eq. 5 plus per-link capacities, solved with scipy's HiGHS; the same tie-break in a
      second solve. Without links it returns exactly what ``paper`` returns.
    """
    try:
        chosen = strategy if isinstance(strategy, Strategy) else Strategy(strategy)
    except ValueError:
        names = ", ".join(s.value for s in Strategy)
        raise SpecError(f"strategy={strategy!r} is not one of: {names}") from None
    rows = _rows(problem, chosen)
    arrays = problem.arrays
    w, fmin, fmax = arrays.size_bytes, arrays.min_rate_hz, arrays.max_rate_hz
    budget = problem.budget_bytes_per_s
    normalized = normalize_priorities(arrays.priority, w)
    if chosen is Strategy.STATIC:
        floors, floor_name = fmin, "minimum rates"
    else:
        floors, floor_name = (fmax - fmin) * normalized + fmin, "priority floors"
    lower, problem_message, scaled_minimums = _relax(w, fmin, floors, rows, floor_name)

    if scaled_minimums:
        rates = lower  # even the minimums do not fit: one common fraction, nothing left to share
    elif chosen is Strategy.PAPER or (chosen is Strategy.LP and not problem.links):
        rates = _fill_ascending_size(w, lower, fmax, budget, arrays.size_order)
    elif chosen is Strategy.FAIR:
        rates = np.clip(_water_level(w, lower, fmax, budget), lower, fmax)
    elif chosen is Strategy.STATIC:
        common = min(budget / float(w.sum()), _water_level(w, lower, fmax, budget))
        rates = np.clip(common, lower, fmax)
    else:
        rates = _solve_lp(w, lower, fmax, rows)

    used = float(w @ rates)
    if problem_message is None:
        status = Status.OPTIMAL
        message = f"{_mbit(used)} of a {_mbit(budget)} budget allocated"
        if problem.frame_headroom:
            message += f" ({_mbit(problem.headroom_bytes_per_s)} kept for whole frames)"
    else:
        status, message = Status.INFEASIBLE, problem_message
    return Allocation(
        strategy=chosen,
        status=status,
        message=message,
        budget_bytes_per_s=budget,
        link_bytes_per_s=problem.link_bytes_per_s,
        topics=problem.topics,
        priority=arrays.priority,
        normalized_priority=_frozen(normalized),
        floor_hz=floors if floors is fmin else _frozen(floors),
        rate_hz=_frozen(rates if rates is not lower else rates.copy()),
        size_bytes=w,
    )
