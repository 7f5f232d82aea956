"""The passive sniffer over a real loopback zenoh session: arrivals, and send times where known."""

from __future__ import annotations

import time

from dbml.harness.processes import free_port
from dbml.harness.sniffer import WireSniffer
from dbml.protocol.metadata import pack_meta
from dbml.transports.zenoh import ZenohTransport
from tests.conftest import wait_for


def test_a_sample_with_dbmls_metadata_is_kept_by_its_send_time_too() -> None:
    port = free_port()
    listener = ZenohTransport(host="sniff", port=port)
    sender = ZenohTransport(host="send", port=port)
    try:
        assert sender.wait_for_peers(10)
        with WireSniffer(listener.session, "r1/**") as sniffer:
            sent_ns = time.time_ns() - 2_000_000_000  # stamped 2 s before it arrives

            def heard() -> bool:
                sender.session.put("r1/cam", b"x" * 10, attachment=pack_meta(1, sent_ns, 4.0))
                sender.session.put("r1/raw", b"y" * 20)  # not dbml's: no send time
                return len(sniffer.arrivals()) >= 2

            wait_for(heard, timeout_s=10, what="the samples at the sniffer")
            sent = sniffer.sent()
            assert sent
            assert all(size == 10 for _, size in sent)
            assert all(abs(t - sent_ns / 1e9) < 1e-6 for t, _ in sent)
            assert {size for _, size in sniffer.arrivals()} == {10, 20}
            assert sniffer.sent(since_s=sent_ns / 1e9 + 1) == []
    finally:
        sender.close()
        listener.close()
