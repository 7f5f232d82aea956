"""The key space: every family built and parsed back by one module."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from dbml.core.errors import TransportError
from dbml.protocol import keys


def test_keys_are_built_under_dbmls_root() -> None:
    assert keys.param_key("/r1/camera/dbm/priority") == "dbml/param/r1/camera/dbm/priority"
    assert keys.data_key("/r1/camera/optimized") == "r1/camera/optimized"
    assert keys.data_key(keys.LINK_TOPIC) == "dbm/link"
    assert keys.own_key("0123456789abcdef", "/dbm/round") == "dbml/own/0123456789abcdef/dbm/round"
    assert keys.global_params_filter() == "dbml/param/dbm/**"
    for family in (keys.PARAM, keys.BATCH, keys.OWN, keys.GRAPH, keys.NODE):
        assert family.startswith(keys.ROOT + "/")


def test_graph_and_node_tokens_round_trip() -> None:
    key = keys.graph_key("sub", "op", "abc.1", "optimized", "/r1/camera")
    assert key == "dbml/graph/sub/op/abc.1/optimized/r1/camera"
    assert keys.parse_graph_key(key) == keys.GraphKey(
        "sub", "op", "abc.1", "optimized", "/r1/camera"
    )
    assert keys.parse_node_key(keys.node_key("0123456789abcdef", "zid1")) == (
        "0123456789abcdef",
        "zid1",
        True,
    )
    robot = keys.node_key("0123456789abcdef", "zid1", follows_all=False)
    assert keys.parse_node_key(robot) == ("0123456789abcdef", "zid1", False)


@pytest.mark.parametrize(
    "key", ["dbml/graph/sub/op", "dbml/node/a/b", "other/graph/sub/op/u/full/t", ""]
)
def test_malformed_graph_tokens_are_none(key: str) -> None:
    assert keys.parse_graph_key(key) is None


@pytest.mark.parametrize(
    "key",
    ["dbml/node/a", "dbml/node/a/b", "dbml/node/a/b/c", "dbml/node/a/b/c/d", "dbml/graph/a/b"],
)
def test_malformed_node_tokens_are_none(key: str) -> None:
    assert keys.parse_node_key(key) is None


def test_owned_names_and_channel_filters() -> None:
    assert keys.own_name("dbml/own/0123456789abcdef/r1/camera/dbm/size") == (
        "0123456789abcdef",
        "/r1/camera/dbm/size",
    )
    assert keys.own_name("dbml/param/x/y") is None
    assert keys.own_name("dbml/own/node") is None
    write = keys.param_key("/r1/camera/dbm/frequency/min")
    assert keys.channel_params_filter(write) == "dbml/param/r1/camera/dbm/**"
    assert keys.channel_params_filter(keys.param_key("/dbm/round")) is None
    assert keys.channel_params_filter("dbml/batch") is None


def test_writes_round_trip_and_malformed_ones_name_what_they_are() -> None:
    assert keys.decode_param(keys.encode_param(0.5, 7, "w")) == (0.5, 7, "w")
    assert keys.decode_batch(keys.encode_batch({"/a": 1, "/b": None}, 9, "w")) == (
        {"/a": 1, "/b": None},
        9,
        "w",
    )
    with pytest.raises(TransportError, match=r"malformed parameter value \[1\]"):
        keys.decode_param(b'{"v": [1], "t": 1, "w": "x"}')
    with pytest.raises(TransportError, match="malformed batch"):
        keys.decode_batch(b'{"vs": 3, "t": 1, "w": "x"}')
    with pytest.raises(TransportError, match="must look like"):
        keys.decode_batch(b'{"vs": {"no slash": 1}, "t": 1, "w": "x"}')


def test_the_wire_schema_is_pure_and_below_the_transports() -> None:
    code = (
        "import sys, dbml.protocol; "
        "bad = [m for m in sys.modules "
        "if m.split('.')[0] in {'zenoh', 'rospy', 'rosgraph', 'rich', 'rosbags'} "
        "or m.startswith(('dbml.runtime', 'dbml.transports', 'dbml.testbed', 'dbml.cli'))]; "
        "print(','.join(sorted(bad)))"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True
    )
    assert result.stdout.strip() == ""


KEY_STRINGS = ("dbml/param", "dbml/batch", "dbml/own", "dbml/graph", "dbml/node", "dbm/link")


@pytest.mark.parametrize("key", KEY_STRINGS)
def test_each_key_family_is_spelled_in_one_module(key: str) -> None:
    source = Path(keys.__file__).parents[1]
    spelled = sorted(
        str(path.relative_to(source))
        for path in source.rglob("*.py")
        if key in path.read_text(encoding="utf-8")
    )
    assert spelled == ["protocol/keys.py"]


def test_node_ids_are_made_and_checked_in_one_place() -> None:
    made = {keys.new_node_id() for _ in range(100)}
    assert len(made) == 100
    assert all(keys.is_node_id(node) for node in made)
    for bad in ("", "0123456789ABCDEF", "0123456789abcde", "0123456789abcdef0", "../own/x"):
        assert not keys.is_node_id(bad), bad
