"""The rclpy store's pure rules: which node a name lives on, and who hosts a node."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from dbml.core.errors import TransportError
from dbml.protocol import schema
from dbml.transports.rclpy.nodes import hosts_it, node_of, yields

participants = st.binary(min_size=12, max_size=12)


def test_names_live_on_the_papers_nodes() -> None:
    assert node_of("/dbm/max_bandwidth_in_mbit")[1:] == ("/dbm", "max_bandwidth_in_mbit")
    assert node_of("/r1/camera/dbm/frequency/min")[1:] == ("/r1/camera/dbm", "frequency.min")
    with pytest.raises(TransportError, match=r"name='/x' is not one of dbml's"):
        node_of("/x")


def test_hosting_follows_the_schemas_writers() -> None:
    """Each node is hosted by the role that alone writes some of it: derived, not listed.

    The optimizer (and its estimator) for ``/dbm``, a channel's publisher for ``[topic]/dbm``.
    """
    hosting = {p.field for p in schema.PARAMETERS if hosts_it(p)}
    assert {"status", "round", "frequency/min", "message_size_in_bytes"} <= hosting
    assert not {"max_bandwidth_in_mbit", "priority", "frequency/current_value"} & hosting


@given(st.sets(participants, min_size=1, max_size=6))
def test_exactly_one_provisional_host_stays(hosts: set[bytes]) -> None:
    staying = [own for own in hosts if not yields(own, hosts, set())]
    assert staying == [min(hosts)]


@given(st.sets(participants, min_size=2, max_size=6), st.data())
def test_every_provisional_host_yields_to_an_owner(hosts: set[bytes], data: st.DataObject) -> None:
    owner = data.draw(st.sampled_from(sorted(hosts)))
    assert all(yields(own, hosts, {owner}) for own in hosts - {owner})


def test_a_lone_host_stays() -> None:
    assert not yields(b"a" * 12, {b"a" * 12}, set())
