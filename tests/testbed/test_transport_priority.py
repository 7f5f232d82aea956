"""A small urgent stream beside saturating cameras: the transport-priority mapping, for real.

One run, ``--policy unmanaged`` (the cameras at 16 Hz want 13.4 Mbit/s of an 11 Mbit/s link,
so R1's frames queue in its socket buffer), R1 sending the 1,000-byte 20 Hz urgent stream twice
at the same moments: mapped (its own zenoh priority link, marked DSCP EF, which the run's shared
link honours) and unmapped (behind the frames).
"""

from __future__ import annotations

import pytest

from dbml.testbed import leftover_namespaces
from dbml.testbed.options import TestbedOptions
from dbml.testbed.result import URGENT_P95_MS
from dbml.testbed.runner import run_teleop_testbed

pytestmark = pytest.mark.integration

STEP_S = 2.0
MIN_RECEIVED = 200
"""Of ~20 s x 20 Hz sent (the first ~3 s wait for the fail-safe minimum, no optimizer runs)."""


def test_the_mapped_urgent_stream_overtakes_queued_frames(netns_privilege: None) -> None:
    options = TestbedOptions.from_flags(policy="unmanaged", step_seconds=STEP_S, urgent_stream=True)
    result = run_teleop_testbed(options)
    assert not result.interrupted
    assert leftover_namespaces(f"dbml-{result.run_id}-") == []
    urgent = {u.name: u for u in result.urgent}
    mapped, unmapped = urgent["mapped"], urgent["unmapped"]
    assert mapped.received >= MIN_RECEIVED, mapped
    assert unmapped.received >= MIN_RECEIVED, unmapped
    assert mapped.latency_p95_ms is not None
    assert unmapped.latency_p95_ms is not None
    assert mapped.latency_p95_ms < URGENT_P95_MS, (mapped, unmapped)
    assert mapped.latency_p95_ms < unmapped.latency_p95_ms, (mapped, unmapped)
    assert result.targets()[f"urgent_p95_under_{URGENT_P95_MS:g}ms"]
