"""The ros1 parameter mirror against a real master: what ``rosparam`` does, the mirror sees."""

from __future__ import annotations

import threading

import pytest

from tests.conftest import wait_for
from tests.ros1.rosnet import RosNet

pytestmark = pytest.mark.integration


def test_rosparam_writes_namespaces_and_deletes_reach_the_mirror(ros: RosNet) -> None:
    from dbml.transports.ros1 import _Ros1Params
    from dbml.transports.rosapi import MasterClient

    ros.rosparam("set", "/keep", "1")
    client = MasterClient(ros.master.uri, caller_id="/params_test")
    params = _Ros1Params(client, "/params_test", "127.0.0.1", "127.0.0.1")
    seen: list[tuple[str, object]] = []
    lock = threading.Lock()

    def record(name: str, value: object) -> None:
        with lock:
            seen.append((name, value))

    def saw(event: tuple[str, object]) -> bool:
        with lock:
            return event in seen

    handle = params.watch(record)
    try:
        assert params.get("/keep") == 1  # the tree the subscription returned
        ros.rosparam("set", "/r1/camera/dbm/priority", "0.7")
        wait_for(lambda: saw(("/r1/camera/dbm/priority", 0.7)), timeout_s=5, what="a set")
        assert params.get("/r1/camera/dbm/priority") == 0.7

        # A namespace written as a dict replaces what was under it.
        ros.rosparam("set", "/r1/camera/dbm", "{priority: 0.2, frequency: {max: 16.0}}")
        wait_for(lambda: saw(("/r1/camera/dbm/frequency/max", 16.0)), timeout_s=5, what="dict")
        assert params.get("/r1/camera/dbm/priority") == 0.2

        ros.rosparam("delete", "/r1/camera")
        wait_for(lambda: saw(("/r1/camera/dbm/frequency/max", None)), timeout_s=5, what="delete")
        assert saw(("/r1/camera/dbm/priority", None))
        assert params.get("/r1/camera/dbm/priority") is None
        assert params.get("/keep") == 1

        # Its own writes are read back at once, and reported like anyone's.
        params.set("/dbm/status", "optimal")
        assert params.get("/dbm/status") == "optimal"
        assert ros.param("/dbm/status") == "optimal"
        wait_for(lambda: saw(("/dbm/status", "optimal")), timeout_s=5, what="own write")
        params.set("/dbm/status", None)
        assert ros.param("/dbm/status") is None
        assert params.snapshot("/dbm") == {}
    finally:
        handle.close()
        params.close()
        client.close()
