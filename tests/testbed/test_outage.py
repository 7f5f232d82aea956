"""A link outage for real: the operator's link down for 3 s, then back (``0:11,6:0,9:11``).

Under dbml with the estimator, the publishers hold their newest message while the link is
silent, the estimator keeps its budget through the outage instead of reading the backlog as
congestion, and after the restoration the wire stays within the budget.
"""

from __future__ import annotations

import subprocess
import sys

import pytest

from dbml.testbed import Network, TestbedError, leftover_namespaces
from dbml.testbed.options import TestbedOptions
from dbml.testbed.runner import run_teleop_testbed

pytestmark = pytest.mark.integration

STEP_S = 3.0
SCHEDULE = "0:11,6:0,9:11"
FIRST_URGENT_S = 4.0
"""The urgent channel's first fresh frame after the restoration: TCP's retransmission timer
has backed off during the outage (0.2, 0.4, 0.8, 1.6 s ...), so the first segment after a
3-s outage may wait up to ~3 s; dbml adds under one frame time."""
MAX_STALE = 12
"""Frames sent before the restoration and delivered after it: what the first
``LINK_SILENCE_S`` put into TCP's buffer (without the hold: ~20 in 3 s, 1 s of both cameras)."""
MIN_BUDGET_AFTER_MBIT = 5.0
"""The budget at the end: without the outage state the backlog read as congestion cut it to
the floor (0.23 Mbit) for the rest of the run."""


def test_an_outage_holds_then_releases_the_urgent_channel_first(netns_privilege: None) -> None:
    """Hold, then the most urgent channel first, and the release within the budget.

    Within it as frames allow: one message per channel over the budget in any 1-s window
    (a token bucket's bound). The release waits until each channel's backlog is heard and
    owes what that backlog carried; before both, fresh frames bunched behind the backlog and
    the worst window read 0.30-2.17 Mbit/s over (ten runs), after them 0.13-0.66 (thirteen).
    """
    options = TestbedOptions.from_flags(
        policy="dbml", step_seconds=STEP_S, link_schedule=SCHEDULE, estimate=True
    )
    result = run_teleop_testbed(options)
    assert not result.interrupted
    assert leftover_namespaces(f"dbml-{result.run_id}-") == []
    (outage,) = result.outages
    assert (outage.start_s, outage.end_s, outage.urgent) == (6.0, 9.0, "R1")
    assert outage.first_fresh_urgent_s is not None
    assert outage.first_fresh_urgent_s < FIRST_URGENT_S, outage
    assert outage.stale <= MAX_STALE, outage
    assert outage.release_over_budget_mbit is not None
    assert result.targets()["budget_kept_within_one_message_per_channel_after_outage_at_9s"], outage
    budget = result.steps[-1].budget_mbit
    assert budget is not None
    assert budget >= MIN_BUDGET_AFTER_MBIT, result.steps[-1]


_PROBE = """
import socket, sys
try:
    socket.create_connection((sys.argv[1], 9), timeout=1).close()
except ConnectionRefusedError:
    pass  # the peer's kernel answered: the link carries packets
except OSError:
    sys.exit(1)
"""
"""Exit 0 when a TCP SYN to port 9 gets any answer (a refusal counts), 1 on silence."""


def _reaches(network: Network, src: str, dst: str) -> bool:
    """Whether ``src`` hears from ``dst`` within 1 s over the testbed's links."""
    argv = network.exec_argv(src, [sys.executable, "-c", _PROBE, network.hosts[dst].address])
    return subprocess.run(argv, capture_output=True, check=False, timeout=10).returncode == 0


def test_a_down_link_carries_nothing_either_way_until_a_rate_is_set(
    netns_privilege: None,
) -> None:
    with Network(link_mbit=8) as network:
        assert _reaches(network, "r1", "op")
        network.take_link_down()
        assert network.link_down
        assert not _reaches(network, "r1", "op")
        assert not _reaches(network, "op", "r2")
        assert _reaches(network, "r1", "r2")  # only the operator's link is down
        network.set_link_rate(4)
        assert not network.link_down
        assert network.link_mbit == 4
        assert _reaches(network, "r1", "op")
        assert _reaches(network, "op", "r2")


def test_a_robots_own_radio_down_cuts_that_robot_alone(netns_privilege: None) -> None:
    with Network(link_mbit=8) as network:
        network.take_link_down(host="r1")
        assert network.down_hosts == {"r1"}
        assert not network.link_down  # the shared link is up
        assert not _reaches(network, "r1", "op")
        assert not _reaches(network, "op", "r1")
        assert not _reaches(network, "r2", "r1")
        assert _reaches(network, "r2", "op")
        network.set_link_rate(6, host="r1")
        assert network.down_hosts == set()
        assert network.uplinks_mbit == {"r1": 6.0}  # the robot's uplink is shaped from now on
        assert _reaches(network, "r1", "op")
        assert _reaches(network, "r2", "r1")


def test_a_host_outside_the_testbed_is_refused(netns_privilege: None) -> None:
    with Network(link_mbit=8) as network, pytest.raises(TestbedError, match="'r9' is not a robot"):
        network.take_link_down(host="r9")
