import itertools

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dbml.runtime import Rate, RateLimiter
from dbml.runtime.rate import PACER_LATE_S, ByteWindow, caught_up_periods
from dbml.transports import ManualClock


def count_allowed(
    limiter: RateLimiter, source_hz: float, seconds: float, start: float = 0.0
) -> int:
    ticks = round(seconds * source_hz)
    return sum(limiter.allow(start + i / source_hz) for i in range(ticks))


@pytest.mark.parametrize(
    ("source_hz", "rate_hz"), [(16, 12.369), (16, 1.476), (100, 13.095), (30, 29)]
)
def test_a_faster_source_gets_exactly_the_rate_on_average(source_hz: float, rate_hz: float) -> None:
    allowed = count_allowed(RateLimiter(rate_hz), source_hz, 100.0)
    assert abs(allowed - rate_hz * 100) <= 1


def test_a_slower_source_loses_nothing() -> None:
    assert count_allowed(RateLimiter(16), 10, 10.0) == 100


def test_a_decrease_applies_from_the_next_message_without_a_burst() -> None:
    limiter = RateLimiter(16)
    sent = [t / 100 for t in range(100) if limiter.allow(t / 100)]  # one second at 16 Hz
    limiter.set_rate(2, 1.0)
    later = [1 + t / 100 for t in range(200) if limiter.allow(1 + t / 100)]
    assert len(sent) == 16
    assert len(later) <= 5  # 2 Hz over two seconds, plus at most the one already due
    gaps = [b - a for a, b in itertools.pairwise(later)]
    assert all(gap >= 0.5 - 1e-9 for gap in gaps)


def test_an_increase_applies_from_the_last_message_not_after_the_old_period() -> None:
    limiter = RateLimiter(1)
    assert limiter.allow(0.0)
    limiter.set_rate(10, 0.0)  # the allocation arrives: 10 Hz, not one more second at 1 Hz
    assert not limiter.allow(0.05)
    assert limiter.allow(0.1)
    assert not limiter.allow(0.15)
    assert limiter.allow(0.2)


def test_rate_sleep_keeps_absolute_deadlines() -> None:
    clock = ManualClock(10.0)
    slept: list[float] = []

    def sleep(seconds: float) -> None:
        slept.append(seconds)
        clock.advance(seconds)

    rate_hz = [4.0]
    rate = Rate(lambda: rate_hz[0], clock=clock, sleep=sleep)
    ticks = []
    for i in range(8):
        clock.advance(0.05 if i % 2 else 0.1)  # loop work of varying length
        rate.sleep()
        ticks.append(clock())
    assert ticks[0] == pytest.approx(10.1)  # the loop's first tick is at once
    gaps = [b - a for a, b in itertools.pairwise(ticks)]
    assert gaps == pytest.approx([0.25] * 7)
    rate_hz[0] = 2.0
    rate.sleep()
    assert clock() - ticks[-1] == pytest.approx(0.5)


def test_rate_sleep_makes_up_for_late_wake_ups() -> None:
    """A sleep that returns late (a busy machine) does not slow the loop: the next is earlier."""
    clock = ManualClock()

    def oversleep(seconds: float) -> None:
        clock.advance(seconds + 0.002)

    rate = Rate(lambda: 16.0, clock=clock, sleep=oversleep)
    for _ in range(161):
        rate.sleep()
    assert clock() == pytest.approx(10.0, abs=0.0625)  # 160 periods, not 160 x 64.5 ms


def test_rate_sleep_does_not_burst_after_falling_behind() -> None:
    clock = ManualClock()
    rate = Rate(lambda: 10.0, clock=clock, sleep=clock.advance)
    rate.sleep()
    clock.advance(5.0)  # the loop stalled for 50 periods
    start = clock()
    rate.sleep()
    rate.sleep()
    assert clock() - start >= 0.1 - 1e-9


def ticks_around_a_stall(rate_hz: float, late_s: float) -> list[float]:
    """A paced loop's ticks when its third tick comes ``late_s`` late (the process stalled)."""
    clock = ManualClock()
    rate = Rate(lambda: rate_hz, clock=clock, sleep=clock.advance)
    ticks = []
    for k in range(12):
        if k == 3:
            clock.advance(1 / rate_hz + late_s)  # stopped through its next tick's time
        rate.sleep()
        ticks.append(clock())
    return ticks


def test_a_stalled_tick_is_not_caught_up() -> None:
    """The next tick after a stall is a period after it: no frame right behind the late one.

    Caught up, R1's next 84,000-B frame went 42 ms after one 141 ms late, onto a 4-Mbit uplink
    where a frame takes 176 ms: it waited 126 ms, and the backlog took 3 s to drain.
    """
    rate_hz = 5.48
    period_s = 1 / rate_hz
    ticks = ticks_around_a_stall(rate_hz, 0.141)
    gaps = [b - a for a, b in itertools.pairwise(ticks)]
    assert max(gaps) == pytest.approx(period_s + 0.141)  # the stall
    assert min(gaps) == pytest.approx(period_s)


@pytest.mark.parametrize("rate_hz", [1.0, 5.48, 16.0, 30.0])
def test_a_tick_late_by_less_than_a_stall_is_caught_up(rate_hz: float) -> None:
    """Late by less than ``caught_up_periods``: the loop stays on its grid (no rate lost)."""
    late_s = 0.9 * caught_up_periods(rate_hz) / rate_hz
    ticks = ticks_around_a_stall(rate_hz, late_s)
    assert ticks[-1] - ticks[0] == pytest.approx((len(ticks) - 1) / rate_hz)


@pytest.mark.parametrize("rate_hz", [5.48, 16.0])
def test_a_stall_costs_the_time_it_took(rate_hz: float) -> None:
    """Late by more: the tick goes at once, and the schedule goes on from it (a restart)."""
    late_s = max(1.2 * PACER_LATE_S, 0.3 / rate_hz)
    ticks = ticks_around_a_stall(rate_hz, late_s)
    assert ticks[-1] - ticks[0] == pytest.approx((len(ticks) - 1) / rate_hz + late_s)


def test_a_new_rate_applies_during_a_long_wait() -> None:
    clock = ManualClock()
    rate_hz = [1.0]

    def sleep(seconds: float) -> None:
        clock.advance(seconds)
        if clock() >= 0.2:
            rate_hz[0] = 16.0  # an allocation arrives 0.2 s into a 1 s period

    rate = Rate(lambda: rate_hz[0], clock=clock, sleep=sleep)
    rate.sleep()
    rate.sleep()
    assert clock() == pytest.approx(0.2, abs=0.06)  # not 1.0


def test_brief_increases_earn_only_their_share() -> None:
    """Churn: 1 Hz with a 16 Hz allocation for 5 ms ten times a second.

    The rate in force averages 1.75 Hz; a limiter that applied each new rate from the last
    message on sent at about 10 Hz, once per increase (priority churn put 1.25 x B on the wire).
    """
    limiter = RateLimiter(1)
    sent = 0
    for step in range(1000):  # 10 s in 10 ms steps, a source at 100 Hz
        now = step / 100
        if step % 10 == 0:
            limiter.set_rate(16, now)
        elif step % 10 == 1:
            limiter.set_rate(1, now - 0.005)
        sent += limiter.allow(now)
    assert sent <= 10 * 1.75 + 2


@settings(max_examples=200, deadline=None)
@given(
    st.lists(
        st.tuples(st.floats(0.001, 0.5), st.floats(0.5, 40.0)),
        min_size=1,
        max_size=40,
    ),
    st.floats(5.0, 200.0),
)
def test_what_goes_out_never_exceeds_the_integral_of_the_rate(
    changes: list[tuple[float, float]], source_hz: float
) -> None:
    """In every window: messages <= integral of the rate in force + the two banked frames."""
    limiter = RateLimiter(changes[0][1])
    segments = []  # (start_s, rate_hz) of the rate in force
    t = 0.0
    for gap_s, rate_hz in changes:
        segments.append((t, rate_hz))
        t += gap_s
    end_s = t
    sent: list[float] = []
    tick = 0
    index = 0
    while (now := tick / source_hz) < end_s:
        while index + 1 < len(segments) and segments[index + 1][0] <= now:
            index += 1
            limiter.set_rate(segments[index][1], segments[index][0])
        if limiter.allow(now):
            sent.append(now)
        tick += 1

    def integral(a: float, b: float) -> float:
        total = 0.0
        for i, (start, rate) in enumerate(segments):
            stop = segments[i + 1][0] if i + 1 < len(segments) else end_s
            total += max(0.0, min(b, stop) - max(a, start)) * rate
        return total

    for i, start in enumerate(sent):
        for window_s in (0.25, 1.0):
            count = sum(1 for s in sent[i:] if s < start + window_s)
            assert count <= integral(start, start + window_s) + 2 + 1e-6


def test_a_restart_keeps_at_most_one_frame_and_owes_what_it_is_told() -> None:
    limiter = RateLimiter(10.0)
    assert limiter.allow(50.0)
    limiter.restart(10.0, 60.0, owed_frames=2.0)  # 10 s idle: one frame kept, two owed
    assert not limiter.allow(60.0)
    assert not limiter.allow(60.19)  # -1 + 1.9 frames: not yet
    assert limiter.allow(60.2)
    assert not limiter.allow(60.2)


def test_restarting_often_never_starves_the_channel() -> None:
    """Each restart keeps what was earned: a flood of them still lets the rate through."""
    limiter = RateLimiter(10.0)
    sent = 0
    for k in range(1000):  # one restart and one message every 10 ms for 10 s
        now = 100.0 + k * 0.01
        limiter.restart(10.0, now)
        sent += limiter.allow(now)
    assert 99 <= sent <= 101


def test_the_limiters_wait_is_the_time_to_its_next_frame() -> None:
    limiter = RateLimiter(2)
    assert limiter.wait_s(0.0) == 0.0  # the first message goes at once
    assert limiter.allow(0.0)
    assert limiter.wait_s(0.2) == pytest.approx(0.3)
    assert not limiter.allow(0.2)  # asking did not spend
    assert limiter.wait_s(0.5) == 0.0
    assert limiter.allow(0.5)


# -- the byte window ---------------------------------------------------------------------------


def _window_bytes(sent: list[tuple[float, int]]) -> int:
    """The most bytes sent in any 1-s window [t, t + 1) opened by a send."""
    return max(sum(n for u, n in sent if t <= u < t + 1.0) for t, _ in sent)


def test_frames_that_keep_to_their_count_are_never_refused() -> None:
    window = ByteWindow()
    assert all(window.admit(i / 16, 20_000 - i % 7, 20_000, rate_hz=16) for i in range(160))
    assert window.refused == 0


def test_frames_over_their_count_cost_later_frames_not_the_budget() -> None:
    window, sent = ByteWindow(), []
    for i in range(320):  # 16 Hz, every frame 20 % over what it was counted at
        now = i / 16
        if window.admit(now, 24_000, 20_000, rate_hz=16):
            sent.append((now, 24_000))
    assert _window_bytes(sent) <= 16 * 20_000 + 2 * 20_000  # the rate's bytes and two frames
    assert 16 / 1.2 <= len(sent) / 20 < 16  # what those bytes carry of the larger frames
    assert window.refused == 320 - len(sent)


@settings(max_examples=300)
@given(
    st.lists(
        st.tuples(
            st.floats(0.001, 0.2),
            st.integers(1, 50_000),
            st.integers(1, 50_000),
            st.sampled_from([0.0, 1.0, 4.0, 16.0, 30.0]),
        ),
        min_size=1,
        max_size=200,
    )
)
def test_no_window_sends_more_than_its_allocations_and_two_frames(
    frames: list[tuple[float, int, int, float]],
) -> None:
    window, now = ByteWindow(), 0.0
    offered: list[tuple[float, float, int]] = []  # (time, allocation in bytes/s, count)
    sent: list[tuple[float, int]] = []
    for gap_s, size, counted, rate_hz in frames:
        now += gap_s
        offered.append((now, rate_hz * counted, counted))
        if window.admit(now, size, counted, rate_hz=rate_hz):
            sent.append((now, size))
    for t, _ in sent:  # every window closed by a send
        went = sum(n for u, n in sent if t - 1.0 < u <= t)
        # In force over (t - 1, t]: the allocation of the last offer before it and each within.
        before = [a for u, a, _ in offered if u <= t - 1.0][-1:]
        within = [(a, c) for u, a, c in offered if t - 1.0 < u <= t]
        largest = max(c for _, c in within)
        assert went <= 2 * largest + max(before + [a for a, _ in within]) * 1.0 + 1e-6


def test_offers_close_together_get_the_rates_frames_and_two() -> None:
    # 20 frames a second at 16 Hz, each at its count: counting what was offered instead would
    # let all 20 go.
    window, sent = ByteWindow(), []
    for i in range(40):
        now = i / 20
        if window.admit(now, 20_000, 20_000, rate_hz=16):
            sent.append((now, 20_000))
    assert _window_bytes(sent) <= 18 * 20_000
    assert window.refused > 0


def test_refused_frames_do_not_widen_the_window() -> None:
    window, sent = ByteWindow(), []
    for i in range(64):  # 32 Hz of frames 10 % over their count, the rate 16 Hz
        now = i / 32
        if window.admit(now, 22_000, 20_000, rate_hz=16):
            sent.append((now, 22_000))
    assert _window_bytes(sent) <= 18 * 20_000


def test_frames_sent_just_before_a_cut_leave_the_lower_rate_its_frames() -> None:
    window = ByteWindow()
    assert all(window.admit(i / 16, 20_000, 20_000, rate_hz=16) for i in range(32))
    # Cut to 8 Hz: the frames after it, at their count, are within what both rates earned.
    assert all(window.admit(2.0 + i / 8, 20_000, 20_000, rate_hz=8) for i in range(16))
    assert window.refused == 0


def test_a_cut_seen_late_counts_from_the_last_frame_at_the_lower_rate() -> None:
    window = ByteWindow()  # 10 Hz at 100 B, then nothing for 0.5 s, then 1 Hz
    assert all(window.admit(i / 10, 100, 100, rate_hz=10) for i in range(10))
    # At 1.4 s the window (0.4, 1.4] holds 5 frames (500 B). Seen at 1.4 s, the cut earns
    # 10 Hz until 0.9 s (500 B) and 1 Hz since (50 B): 750 B with two frames, not 1,200.
    assert not window.admit(1.4, 300, 100, rate_hz=1)
    assert window.admit(1.4001, 200, 100, rate_hz=1)


def test_a_frame_counts_from_when_it_left_not_from_when_it_was_offered() -> None:
    window = ByteWindow()  # 1 Hz at 100 B: the rate's frame and one more, 200 B a window
    assert window.admit(0.0, 150, 100, rate_hz=1)
    window.left(0.05)  # its send took 50 ms
    assert window.admit(0.5, 50, 100, rate_hz=1)
    window.left(0.5)
    # Offered 1.02 s after the first but 0.97 s after it left: a wire window holds all three.
    assert not window.admit(1.02, 150, 100, rate_hz=1)
    assert window.admit(1.06, 150, 100, rate_hz=1)


def test_a_lower_rung_keeps_the_frames_of_the_higher_one_in_its_window() -> None:
    # 16 Hz at 12,000 B, then a rung of 2,500 B whose frames come 1 ms early: each window
    # then opens just before a large frame and holds one more of them than their rate earned
    # in it. Every frame at its count.
    window = ByteWindow()
    assert all(window.admit(i / 16, 12_000, 12_000, rate_hz=16) for i in range(32))
    assert all(window.admit(2.0 + i / 16 - 1e-3, 2_500, 2_500, rate_hz=16) for i in range(32))
    assert window.refused == 0


def test_the_window_remembers_a_bounded_number_of_frames() -> None:
    # At 0 Hz two frames at their count fill the window, unless the window forgot one.
    whole, bounded = ByteWindow(), ByteWindow(max_frames=2)
    for window in (whole, bounded):
        assert window.admit(0.0, 20, 10, rate_hz=0)
        assert not window.admit(0.001, 10, 10, rate_hz=0)
    assert not whole.admit(0.002, 10, 10, rate_hz=0)
    assert bounded.admit(0.002, 10, 10, rate_hz=0)
