"""The ros1 parameter sync's pushes kept while it subscribes are bounded (a fake master)."""

from __future__ import annotations

import logging
import threading
import xmlrpc.client
from collections.abc import Iterator
from xmlrpc.server import SimpleXMLRPCServer

import pytest

from dbml.transports.ros1 import params as ros1_params
from dbml.transports.ros1.master import MasterClient
from dbml.transports.ros1.params import Ros1Params

BOUND = 64
"""The pushes kept while subscribing, for the test (``MAX_EARLY_PUSHES``, 4,096, took 17 s)."""
OVER = 10
PUSHES = BOUND + OVER
SUBSCRIBE_TIMEOUT_S = 60.0


class FakeMaster:
    """Answers the calls the mirror makes; floods it with pushes while it subscribes."""

    def __init__(self) -> None:
        self.server = SimpleXMLRPCServer(("127.0.0.1", 0), logRequests=False, allow_none=True)
        self.uri = f"http://127.0.0.1:{self.server.server_address[1]}/"
        self.reads = 0
        for name in ("subscribeParam", "getParam", "unsubscribeParam"):
            self.server.register_function(getattr(self, name), name)
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def subscribeParam(self, _caller: str, api: str, _key: str) -> list[object]:  # noqa: N802
        pusher = xmlrpc.client.ServerProxy(api)
        for i in range(PUSHES):  # newer than the tree returned below
            pusher.paramUpdate("/master", f"/flood/{i}/", i)
        return [1, "", {"keep": 1}]

    def getParam(self, _caller: str, _key: str) -> list[object]:  # noqa: N802
        self.reads += 1
        return [1, "", {"keep": 1, "flood": {str(i): i for i in range(PUSHES)}}]

    def unsubscribeParam(self, *_args: object) -> list[object]:  # noqa: N802
        return [1, "", 1]

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture
def master() -> Iterator[FakeMaster]:
    fake = FakeMaster()
    yield fake
    fake.close()


def test_pushes_past_the_bound_while_subscribing_are_read_again_whole(
    master: FakeMaster, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(ros1_params, "MAX_EARLY_PUSHES", BOUND)
    # The fake master pushes from inside the subscription's call: thousands of calls, which a
    # loaded machine takes seconds for, beyond a real call's timeout.
    client = MasterClient(master.uri, caller_id="/early_test", timeout_s=SUBSCRIBE_TIMEOUT_S)
    with caplog.at_level(logging.WARNING, logger="dbml.ros1"):
        params = Ros1Params(client, "/early_test", "127.0.0.1", "127.0.0.1")
    try:
        assert params._early is None  # pushes apply directly from now on
        assert master.reads == 1  # the whole tree, read once again
        assert params.replica.get("/keep") == 1
        assert params.replica.get("/flood/0") == 0
        assert params.replica.get(f"/flood/{PUSHES - 1}") == PUSHES - 1  # dropped, then read
        assert [r.getMessage() for r in caplog.records] == [
            f"{PUSHES} parameter pushes arrived while subscribing, more than the "
            f"{BOUND} kept: reading every parameter again"
        ]
    finally:
        params.close()
