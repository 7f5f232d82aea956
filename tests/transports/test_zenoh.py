"""The zenoh transport's own bookkeeping, on loopback."""

from __future__ import annotations

from dbml.harness.processes import free_port
from dbml.transports import Variant
from dbml.transports.zenoh import ZenohTransport


def test_closed_declarations_are_forgotten() -> None:
    with ZenohTransport(host="solo", port=free_port()) as transport:
        baseline = len(transport._declared)
        for variant in [Variant.FULL, Variant.OPTIMIZED] * 5:  # a subscriber flipping variants
            transport.subscribe("/r1/camera", lambda _s: None, variant).close()
            transport.declare_publisher("/r1/camera", variant).close()
        assert len(transport._declared) == baseline
        kept = transport.subscribe("/r1/camera", lambda _s: None)
        assert len(transport._declared) == baseline + 1
        kept.close()
        kept.close()
        assert len(transport._declared) == baseline
    assert transport._declared == set()
