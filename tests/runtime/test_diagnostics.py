"""The optimizer's statuses: OK, WARN when infeasible, ERROR for a channel sending nothing."""

from dbml.core.allocation import Status, Strategy
from dbml.protocol.messages import ChannelRound, RoundReport
from dbml.runtime.diagnostics import OPTIMIZER_NAME, Level, channel_name, statuses


def report(status: Status, *channels: ChannelRound) -> RoundReport:
    return RoundReport(
        round=7,
        status=status,
        message="optimal" if status is Status.OPTIMAL else "minimums need 9 Mbit/s",
        strategy=Strategy.PAPER,
        budget_mbit=11.0,
        channels=channels,
    )


def camera(topic: str, *, managed: bool = True, sent_hz: float | None = 12.0) -> ChannelRound:
    return ChannelRound(
        topic=topic,
        managed=managed,
        priority=0.5,
        min_hz=1.0,
        max_hz=16.0,
        size_bytes=84_000.0,
        rate_hz=12.37,
        share=0.75,
        sent_hz=sent_hz,
        encoding="x1 q80",
    )


def test_an_optimal_round_is_ok_with_one_status_per_channel() -> None:
    found = statuses(report(Status.OPTIMAL, camera("/r1/camera"), camera("/r2/camera")))
    assert [s.name for s in found] == [OPTIMIZER_NAME, "dbml: /r1/camera", "dbml: /r2/camera"]
    assert {s.level for s in found} == {Level.OK}
    values = dict(found[1].values)
    assert values["allocated_hz"] == "12.370"
    assert values["sent_hz"] == "12.000"
    assert values["bytes_per_s"] == "1008000"
    assert values["rung"] == "x1 q80"
    assert dict(found[0].values)["allocated_mbit"] == f"{2 * 12.37 * 84_000 * 8 / 1e6:.3f}"


def test_an_infeasible_round_warns_for_the_optimizer_and_its_managed_channels() -> None:
    found = statuses(
        report(Status.INFEASIBLE, camera("/r1/camera"), camera("/r2/camera", managed=False))
    )
    levels = {s.name: s.level for s in found}
    assert levels == {
        OPTIMIZER_NAME: Level.WARN,
        channel_name("/r1/camera"): Level.WARN,
        channel_name("/r2/camera"): Level.OK,  # unmanaged: at its maximum, not held back
    }
    assert found[0].message == "infeasible: minimums need 9 Mbit/s"


def test_a_managed_channel_sending_nothing_is_an_error_even_when_infeasible() -> None:
    for status in Status:
        found = statuses(report(status, camera("/r1/camera", sent_hz=0.0)))
        assert found[1].level is Level.ERROR
    unsaid = statuses(report(Status.OPTIMAL, camera("/r1/camera", sent_hz=None)))
    assert unsaid[1].level is Level.OK  # not said yet is not nothing sent
    idle = statuses(report(Status.OPTIMAL, camera("/r1/camera", managed=False, sent_hz=0.0)))
    assert idle[1].level is Level.OK  # unmanaged: nothing goes on the optimized copy
