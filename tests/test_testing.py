"""dbml.testing's fleet: the product's parts on one in-memory network and one clock."""

from __future__ import annotations

import pytest

from dbml import DbmSettings
from dbml.core import SpecError, TransportError
from dbml.protocol import names
from dbml.testing import BASE, FIRST_TIME_S, Fleet
from dbml.transports import MemoryTransport


def test_a_fleet_runs_table2_s_first_step_and_delivers_to_the_operator() -> None:
    with Fleet(settings=DbmSettings(max_bandwidth_mbit=11)) as fleet:
        r1 = fleet.publisher("/r1/camera", size_bytes=84_000)
        fleet.publisher("/r2/camera", size_bytes=21_000)
        fleet.watch("/r1/camera")
        fleet.watch("/r2/camera")
        fleet.priority("/r2/camera", 10 / 17)
        result = fleet.optimize()
        assert fleet.get(names.STATUS) == "optimal"
        assert {t: round(r, 2) for t, r in fleet.rates().items()} == {
            "/r1/camera": 12.37,
            "/r2/camera": 16.0,
        }
        assert result.rates_hz == pytest.approx(fleet.rates())
        assert not r1.publish(bytes(84_000))  # the first frame spent the credit of this instant
        fleet.advance(0.1)  # more than a period at 12.37 Hz
        assert r1.publish(bytes(84_000))
        assert [len(s.payload) for s in fleet.received["/r1/camera"]] == [84_000]
    # Closed with the fleet: every declaration withdrawn, as the processes' exits would.
    assert MemoryTransport(fleet.network, host="after").graph.entries() == frozenset()
    with pytest.raises(TransportError, match="closed"):
        fleet.operator.declare_publisher("/r1/camera")


def test_the_clock_is_the_fleet_s_and_moves_only_when_told() -> None:
    fleet = Fleet(optimizer=False)
    camera = fleet.publisher("/r1/camera", size_bytes=1_000)
    assert fleet.clock() == FIRST_TIME_S
    fleet.allocate("/r1/camera", 4.0)
    assert fleet.get(names.current_value("/r1/camera")) == 4.0
    assert camera.current_rate_hz() == 4.0
    fleet.advance(10.0)  # 10 periods without a heartbeat: fail-safe
    assert fleet.clock() == FIRST_TIME_S + 10.0
    assert camera.current_rate_hz() == 1.0
    assert fleet.host(BASE) is fleet.host(BASE)
    fleet.close()


def test_a_fleet_without_an_optimizer_says_so() -> None:
    with pytest.raises(SpecError, match="optimizer=False takes none"):
        Fleet(optimizer=False, settings=DbmSettings(max_bandwidth_mbit=1))
    with Fleet(optimizer=False) as fleet, pytest.raises(SpecError, match="no optimizer"):
        fleet.optimize()
    with Fleet(clock=lambda: 0.0) as fleet, pytest.raises(SpecError, match="manual clock"):
        fleet.advance(1.0)
