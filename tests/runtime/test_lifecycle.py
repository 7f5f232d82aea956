"""The managed optimizer's transitions, on the memory transport with the optimizer's thread."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import pytest

from dbml.core import DbmSettings
from dbml.protocol import names
from dbml.runtime.lifecycle import LifecycleError, OptimizerLifecycle
from dbml.runtime.serve import OptimizerRun
from dbml.testing import BASE, Fleet
from tests.conftest import wait_for

R1, R2 = "/r1/camera", "/r2/camera"
PERIOD_S = 0.1
STEP1 = {R1: 12.37, R2: 16.0}
"""Table 2's step 1 (R2's priority 10/17 of R1's)."""
FLOORS = {R1: 1.0, R2: 1.0}
"""Each publisher's minimum: where it runs with no optimizer (its fail-safe)."""


@pytest.fixture
def fleet() -> Iterator[Fleet]:
    """Table 1's robots and an operator watching both, no optimizer of the fleet's own."""
    with Fleet(optimizer=False, clock=time.monotonic) as made:
        made.publisher(R1, size_bytes=84_000)
        made.publisher(R2, size_bytes=21_000)
        made.watch(R1)
        made.watch(R2)
        made.priority(R2, 10 / 17)
        yield made


def rounded(fleet: Fleet) -> dict[str, float]:
    return {topic: round(rate, 2) for topic, rate in fleet.rates().items()}


def lifecycle_of(fleet: Fleet, stop: threading.Event) -> OptimizerLifecycle:
    return OptimizerLifecycle(
        lambda: OptimizerRun(fleet.host(BASE), settings=DbmSettings(11.0, 1.0, PERIOD_S), links=()),
        stop=stop,
    )


def test_active_allocates_and_inactive_leaves_the_channels_as_with_no_optimizer(
    fleet: Fleet,
) -> None:
    stop = threading.Event()
    lifecycle = lifecycle_of(fleet, stop)
    try:
        lifecycle.configure()
        run = lifecycle.run
        assert run is not None
        assert run.node.last_round is None  # configured is idle: not one round
        assert fleet.get(names.ROUND) is None
        lifecycle.activate()
        wait_for(lambda: rounded(fleet) == STEP1, timeout_s=5, what="Table 2's step 1")
        lifecycle.deactivate()
        heartbeat = fleet.get(names.ROUND)
        # silence for the fail-safe's periods: each publisher back at its minimum
        wait_for(lambda: fleet.rates() == FLOORS, timeout_s=5, what="the fail-safe's minimum")
        assert all(p.failsafe for p in fleet.publishers.values())
        assert fleet.get(names.ROUND) == heartbeat  # no heartbeat while inactive
        lifecycle.activate()
        wait_for(lambda: rounded(fleet) == STEP1, timeout_s=5, what="step 1 again")
        assert not stop.is_set()
        lifecycle.cleanup()
        assert lifecycle.run is None
        heartbeat = fleet.get(names.ROUND)
        wait_for(lambda: fleet.rates() == FLOORS, timeout_s=5, what="the minimum after cleanup")
        assert fleet.get(names.ROUND) == heartbeat  # closed: its rounds ended
        lifecycle.shutdown()
        assert stop.is_set()
    finally:
        lifecycle.close()


def test_a_transition_the_state_does_not_allow_is_refused_naming_it(fleet: Fleet) -> None:
    lifecycle = lifecycle_of(fleet, threading.Event())
    for transition in (lifecycle.activate, lifecycle.deactivate, lifecycle.cleanup):
        with pytest.raises(LifecycleError, match=f"transition='{transition.__name__}'"):
            transition()
    lifecycle.configure()
    with pytest.raises(LifecycleError, match="configured already"):
        lifecycle.configure()
    lifecycle.shutdown()
    assert lifecycle.run is None
