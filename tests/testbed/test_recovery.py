"""Every stream comes back after an outage: of the shared link or of one robot's radio.

An outage of zenoh's default lease (10 s) outlasts dbml's (3 s): the sessions to every peer
behind the link close, and zenoh closes each lost TCP link with a 10-s ``SO_LINGER`` on a
thread of its receiving runtime. With zenoh's two threads, two such closes held every link, new
ones included, until the lost data was acknowledged after the return: the roles met again
4.7-5.4 s after the link came back (docs/testbed.md). A 1-s outage keeps the sessions: TCP's
retransmission does the work. Here the shared link goes down for 1 s (peers) and for 10 s
(behind a router, the case that once took 4 s), and R1's radio alone for 10 s (peers): each
mechanism once. ``bench/outage.py`` runs the whole matrix (both scopes, both lengths, both
topologies) many times.
"""

from __future__ import annotations

import pytest

from dbml.experiment.analysis import OUTAGE_RECOVERY_S
from dbml.experiment.analysis.outage import LINK_SCOPE
from dbml.testbed import leftover_namespaces
from dbml.testbed.options import TestbedOptions
from dbml.testbed.runner import run_teleop_testbed

pytestmark = pytest.mark.integration

STEP_S = 3.0
DOWN_AT_S = 9.0
LEASE_S = 10.0


def _schedule(outage_s: float) -> str:
    return f"0:11,{DOWN_AT_S:g}:0,{DOWN_AT_S + outage_s:g}:11"


@pytest.mark.parametrize(
    ("scope", "outage_s", "topology"),
    [
        (LINK_SCOPE, 1.0, "peer"),
        (LINK_SCOPE, LEASE_S, "router"),
        ("R1", LEASE_S, "peer"),
    ],
)
def test_every_robot_behind_the_link_delivers_its_allocation_soon_after_it_returns(
    netns_privilege: None, scope: str, outage_s: float, topology: str
) -> None:
    spec = _schedule(outage_s)
    options = TestbedOptions.from_flags(
        policy="dbml",
        estimate=True,
        step_seconds=STEP_S,
        topology=topology,
        link_schedule=spec if scope == LINK_SCOPE else None,
        uplink_schedules=() if scope == LINK_SCOPE else (f"{scope}={spec}",),
    )
    result = run_teleop_testbed(options)
    assert not result.interrupted
    assert leftover_namespaces(f"dbml-{result.run_id}-") == []
    behind = {"R1", "R2"} if scope == LINK_SCOPE else {scope}
    assert {r.robot for r in result.recoveries} == behind
    robots = [r.robot for r in result.steps[0].robots]
    for recovery in result.recoveries:
        assert recovery.scope == scope
        assert recovery.back_s == DOWN_AT_S + outage_s
        assert recovery.back_within(OUTAGE_RECOVERY_S), recovery
        # the outage was real: nothing of the robot arrived while its link was down
        k = robots.index(recovery.robot)
        silent = [
            p.robots[k].delivered_hz
            for p in result.series
            if DOWN_AT_S + 1 + 1e-9 < p.t_s <= DOWN_AT_S + outage_s + 1e-9
        ]
        assert all(hz == 0 for hz in silent), silent
    back = f"every_robot_back_within_{OUTAGE_RECOVERY_S:g}s_after_{scope}_outage_at"
    assert [v for k, v in result.targets().items() if k.startswith(back)] == [True]
