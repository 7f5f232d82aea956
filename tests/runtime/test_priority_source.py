import pytest

from dbml.core import SpecError
from dbml.protocol import names
from dbml.runtime import PrioritySource, collision_priority_source
from dbml.transports import MemoryNetwork, MemoryTransport


def test_collision_source_follows_eq6_eq7_and_writes_only_changes() -> None:
    network = MemoryNetwork()
    observer = MemoryTransport(network, host="op")
    writes: list[object] = []
    observer.params.watch(
        lambda n, v: writes.append(v) if n == names.priority("/r1/camera") else None
    )
    source = collision_priority_source(MemoryTransport(network, host="r1"), "/r1/camera")
    assert source.update(1.25, 0.125) == pytest.approx(10 / 17)  # tc 10 s
    assert source.update(2.5, 0.25) == pytest.approx(10 / 17)  # tc 10 s again: no write
    assert source.update(1.0, 0.0) == 0.0  # stopped: tc = inf
    assert source.update(0.5, 0.5) == 1.0  # tc 1 s
    assert writes == [pytest.approx(10 / 17), 0.0, 1.0]


def test_direct_priority_is_validated() -> None:
    source = PrioritySource(MemoryTransport(), "/cam", lambda x: x)
    assert source.set(0.25) == 0.25
    with pytest.raises(SpecError, match=r"channel '/cam': priority=1.5 must be within \[0, 1\]"):
        source.set(1.5)
    with pytest.raises(SpecError, match=r"speed_m_per_s=-1.0 must be >= 0$"):
        collision_priority_source(MemoryTransport(), "/cam").update(1.0, -1.0)
