"""``Rate(keep_phase=True)``: a loop keeps its own phase across rate changes.

An optimizer pushes a new allocation to every publisher at once; a loop that restarted its
schedule from the change would line up with every other loop slowed by the same push.
"""

from __future__ import annotations

import itertools
import random

import pytest

from dbml.runtime import Rate, RateLimiter
from dbml.transports import ManualClock


def ticks_of(rate: Rate, clock: ManualClock, until_s: float) -> list[float]:
    ticks = []
    while clock() < until_s:
        rate.sleep()
        ticks.append(clock())
    return ticks


@pytest.mark.parametrize("phase_s", [0.0, 0.125, 0.375, 0.5, 0.875])
def test_a_loop_slowed_by_a_push_keeps_its_phase(phase_s: float) -> None:
    """1 Hz from its phase, 11.06 Hz from 3.02 s, 1 Hz again from 6.02 s: the phase stays."""
    clock = ManualClock(phase_s)
    rate_hz = [1.0]

    def sleep(seconds: float) -> None:
        clock.advance(seconds)
        rate_hz[0] = 11.06 if 3.02 <= clock() < 6.02 else 1.0

    rate = Rate(lambda: rate_hz[0], clock=clock, sleep=sleep, keep_phase=True)
    ticks = ticks_of(rate, clock, 12.0)
    slow = [t for t in ticks if t >= 7.0]
    assert slow
    assert all(abs((t - phase_s + 0.5) % 1.0 - 0.5) < 1e-6 for t in slow), slow


def last_phase_after_a_push(phase_s: float, *, keep_phase: bool) -> float:
    """A loop at 16 Hz from ``phase_s``, slowed to 1 Hz by a push at 3.01 s: its last phase."""
    clock = ManualClock(phase_s)

    def rate_hz() -> float:
        return 16.0 if clock() < 3.01 else 1.0

    rate = Rate(rate_hz, clock=clock, sleep=clock.advance, poll_s=0.01, keep_phase=keep_phase)
    return ticks_of(rate, clock, 8.0)[-1] % 1.0


def test_without_keep_phase_the_push_sets_the_phase() -> None:
    """The default (unchanged): two loops spread 0.5 s apart end up together after the push."""
    first, second = (last_phase_after_a_push(p, keep_phase=False) for p in (0.0, 0.5))
    assert first == pytest.approx(second, abs=0.07)
    first, second = (last_phase_after_a_push(p, keep_phase=True) for p in (0.0, 0.5))
    assert abs(first - second) == pytest.approx(0.5, abs=1e-6)


def test_keep_phase_costs_at_most_half_a_frame_per_change() -> None:
    """Ticks up to any moment: at most the rate's integral, the first tick and half a frame.

    Half a frame per change: the tick on the loop's grid may come up to half a period early.
    """
    clock = ManualClock(0.3)
    schedule = [(0.0, 2.0), (1.37, 7.0), (2.05, 0.5), (5.11, 16.0), (5.2, 1.0), (9.0, 3.0)]

    def hz_at(t_s: float) -> float:
        return next(r for at, r in reversed(schedule) if t_s >= at + 0.3)

    rate = Rate(lambda: hz_at(clock()), clock=clock, sleep=clock.advance, keep_phase=True)
    ticks = ticks_of(rate, clock, 13.0)
    assert len(ticks) > 10
    for a, b in itertools.pairwise(ticks):
        assert b - a >= 1 / 16.0 - 1e-9  # never faster than the fastest rate
    for k, end in enumerate(ticks):
        steps = 10_000
        integral = sum(hz_at(0.3 + (end - 0.3) * (i + 0.5) / steps) for i in range(steps))
        integral *= (end - 0.3) / steps
        changes = sum(1 for at, _ in schedule[1:] if at + 0.3 <= end)
        assert k + 1 <= integral + 0.5 * changes + 1 + 1e-6, (end, k + 1, integral)


@pytest.mark.parametrize("change_s", [0.05, 0.11, 0.2, 0.3])
def test_a_new_rate_never_ticks_sooner_than_the_faster_period(change_s: float) -> None:
    """Two ticks are at least the period of the faster of the rates at them apart.

    1.93 Hz, 2.69 Hz from ``change_s`` after a tick, then 1.0 and 3.0 Hz, then 2.92, 1.9 and
    2.69 Hz again before the grid's point at 1.9 Hz. Two ways it failed: the nearest point of
    the grid came 223 ms after the tick before at 1.93 Hz, then 2.69 (a camera's 84 KB frame
    onto a link at 95 % of its rate); and the credit earned while it waited for the grid went
    out as two frames 49 ms apart once the rate was back near the last tick's.
    """
    clock = ManualClock(0.0)
    schedule = [
        (0.0, 1.93),
        (3 / 1.93 + change_s, 2.69),
        (5.37, 1.0),
        (8.61, 3.0),
        (12.0, 2.92),
        (14.0 + change_s, 1.9),
        (14.55, 2.69),
    ]

    def hz_at(t_s: float) -> float:
        return next(r for at, r in reversed(schedule) if t_s >= at)

    rate = Rate(lambda: hz_at(clock()), clock=clock, sleep=clock.advance, keep_phase=True)
    ticks = ticks_of(rate, clock, 18.0)
    assert len(ticks) > 30
    for a, b in itertools.pairwise(ticks):
        assert b - a >= 1 / max(hz_at(a), hz_at(b)) - 1e-9, (a, b)


def test_keep_phase_at_a_steady_rate_is_the_plain_schedule() -> None:
    clock = ManualClock(10.0)
    rate = Rate(lambda: 4.0, clock=clock, sleep=clock.advance, keep_phase=True)
    ticks = ticks_of(rate, clock, 12.0)
    assert [b - a for a, b in itertools.pairwise(ticks)] == pytest.approx([0.25] * (len(ticks) - 1))


def sent_through_a_limiter(phase_s: float, push_s: float, *, keep_phase: bool) -> int:
    """What a managed publisher's limiter lets out of its loop's ticks, 15 s of pushes.

    One allocation, 16, 1, 11.06, 1, 16, 1 Hz: the limiter applies each push at once, the loop
    when it looks next.
    """
    clock = ManualClock(phase_s)
    changes = [(push_s + 3.0 * k, hz) for k, hz in enumerate((1.0, 11.06, 1.0, 16.0, 1.0))]
    limiter = RateLimiter(16.0)
    applied: list[float] = []

    def rate_hz() -> float:
        for at, hz in changes:
            if at <= clock() and at not in applied:
                applied.append(at)
                limiter.set_rate(hz, at)
        return limiter.rate_hz

    rate = Rate(rate_hz, clock=clock, sleep=clock.advance, keep_phase=keep_phase)
    sent = 0
    while clock() < push_s + 15.0:
        rate.sleep()
        sent += limiter.allow(clock())
    return sent


@pytest.mark.parametrize("phase_s", [0.0, 0.13, 0.49, 0.875])
@pytest.mark.parametrize("push_s", [3.0, 3.004, 3.03, 3.2, 3.7])
def test_keeping_the_phase_sends_about_what_the_plain_loop_sends(
    phase_s: float, push_s: float
) -> None:
    """Five changes cost at most two frames of about 130.

    A tick on the grid may wait, or come early for the limiter, which refuses it (the plain
    loop has such ticks too: the limiter hears a push before the loop does).
    """
    plain = sent_through_a_limiter(phase_s, push_s, keep_phase=False)
    kept = sent_through_a_limiter(phase_s, push_s, keep_phase=True)
    assert kept >= plain - 2, (kept, plain)


def sent_by_a_paced_limited_loop(seed: int, *, noise: bool) -> list[float]:
    """A publisher's loop and limiter: 16 Hz, 1 Hz from 3.01 s; each wake-up 0.2-5 ms late.

    With ``noise`` the allocation reads 1 + 1e-14 Hz from 8.2 to 8.27 s (a solver's rounding).
    """
    jitter = random.Random(seed)
    clock = ManualClock(jitter.uniform(0.0, 1.0))

    def rate_hz() -> float:
        now = clock()
        if now < 3.01:
            return 16.0
        return 1.0 + 1e-14 if noise and 8.2 <= now < 8.27 else 1.0

    def sleep(seconds: float) -> None:
        clock.advance(seconds + jitter.uniform(0.0002, 0.005))

    rate = Rate(rate_hz, clock=clock, sleep=sleep, poll_s=0.05, keep_phase=True)
    limiter = RateLimiter(16.0)
    sent = []
    while clock() < 14.0:
        rate.sleep()
        now = clock()
        limiter.set_rate(rate_hz(), now)
        if limiter.allow(now):
            sent.append(now)
    return sent


@pytest.mark.parametrize("noise", [False, True])
def test_a_slowed_loop_late_by_its_wake_ups_loses_no_frame_to_its_limiter(noise: bool) -> None:
    """Every 1-Hz frame goes, a second after the one before (plus a wake-up's lateness).

    Two ways it failed: the limiter dropped its banked credit at the decrease, and an on-time
    tick after a late one found less than a frame (refused: 2 s without a frame, 60 of 300
    patterns); and the loop took float noise for a new rate and realigned (1.1 s, 5 of 300).
    """
    for seed in range(100):
        sent = sent_by_a_paced_limited_loop(seed, noise=noise)
        gaps = [(a, b - a) for a, b in itertools.pairwise(sent) if a > 5.0]
        assert max(gap for _, gap in gaps) < 1.01, (seed, [g for g in gaps if g[1] >= 1.01])


@pytest.mark.parametrize("phase_s", [0.0, 0.21, 0.66])
def test_a_loop_probed_up_in_small_steps_keeps_its_pace(phase_s: float) -> None:
    """2.8 Hz, then 1.5 % more every 200 ms (an estimator's probe): no tick waits past a period.

    Realigning to the grid at each step put the next tick at a new point of a new grid each
    time: the loop went up to 0.7 s without a tick.
    """
    clock = ManualClock(phase_s)

    def hz_at(t_s: float) -> float:
        steps = int((t_s - phase_s - 3.0) / 0.2) + 1 if t_s >= phase_s + 3.0 else 0
        return 2.8 * 1.015 ** min(steps, 20)

    rate = Rate(lambda: hz_at(clock()), clock=clock, sleep=clock.advance, keep_phase=True)
    ticks = ticks_of(rate, clock, phase_s + 10.0)
    gaps = [b - a for a, b in itertools.pairwise(ticks)]
    assert max(gaps) <= 1 / 2.8 + 0.05 + 1e-9, max(gaps)  # a period and a poll at most
