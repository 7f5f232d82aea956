"""dbml's key space on a zenoh network, and the encoding of what travels under it.

Every key family is spelled here once; the zenoh transport, the rmw_zenoh-format transport and a
secure fleet's access rules build their keys from these functions and constants.

| family | key | what travels |
|---|---|---|
| data | ``r1/camera``, ``r1/camera/optimized`` | a channel's messages (topic without its ``/``) |
| parameter | ``dbml/param/<name>`` | one write: ``{"v": value, "t": stamp_ns, "w": writer}`` |
| batch | ``dbml/batch[/<host>]`` | a round: ``{"vs": {name: value}, "t", "w"}``; or one host's |
| owned | ``dbml/own/<node id>/<name>`` | what a session serves to a newcomer (queryable) |
| graph | ``dbml/graph/<role>/<host>/<uid>/<variant>/<topic>`` | a declaration (liveliness) |
| node | ``dbml/node/<node id>/<zenoh id>/<all or own>`` | a session and what it follows |
| link | ``dbm/link`` (topic ``/dbm/link``) | the estimator's beacon |
| round | ``dbm/optimizer/round`` | the optimizer's report (``dbml.protocol.messages``) |
| reception | ``dbm/reception`` (topic ``/dbm/reception``) | what subscribers received |
"""

from __future__ import annotations

import json
import re
import uuid
from collections.abc import Mapping
from dataclasses import dataclass

from dbml.core.errors import TransportError
from dbml.core.spec import short_repr
from dbml.protocol.names import check_topic
from dbml.protocol.schema import GLOBAL_PREFIX, ParamValue, check_param_value, split_channel_name

__all__ = [
    "ALLOCATION_TOPIC",
    "BATCH",
    "GRAPH",
    "LINK_TOPIC",
    "MAX_WRITE_BYTES",
    "NODE",
    "OWN",
    "PARAM",
    "RECEPTION_TOPIC",
    "ROOT",
    "ROUND_TOPIC",
    "GraphKey",
    "batch_key",
    "channel_params_filter",
    "data_key",
    "decode_batch",
    "decode_param",
    "encode_batch",
    "encode_param",
    "global_params_filter",
    "graph_key",
    "is_host_name",
    "is_node_id",
    "new_node_id",
    "node_filter",
    "node_key",
    "own_key",
    "own_name",
    "param_key",
    "parse_graph_key",
    "parse_node_key",
    "topic_graph_filter",
    "topic_params_filter",
]

ROOT = "dbml"
"""Everything of dbml's own (not a channel's data) lives below this chunk."""
PARAM = f"{ROOT}/param"
BATCH = f"{ROOT}/batch"
OWN = f"{ROOT}/own"
GRAPH = f"{ROOT}/graph"
NODE = f"{ROOT}/node"
LINK_TOPIC = f"{GLOBAL_PREFIX}/link"
"""The estimator's beacon: a topic of dbml's own namespace, carried like a channel's data."""
RECEPTION_TOPIC = f"{GLOBAL_PREFIX}/reception"
"""What managed subscribers received, reported to the estimator."""
ROUND_TOPIC = f"{GLOBAL_PREFIX}/optimizer/round"
"""What each optimizer round decided (``dbml.protocol.messages.RoundReport``)."""
ALLOCATION_TOPIC = f"{GLOBAL_PREFIX}/allocation"
"""Over rclpy, the optimizer's whole allocation, from its ``/dbm`` node to the channels' nodes
(``std_msgs/msg/String``, this module's batch encoding); its publisher also says that the
``/dbm`` node is claimed."""
MAX_WRITE_BYTES = 1 << 20
"""A received message larger than this is not a parameter write (nor a batch of them)."""
_SHOWN_CHARS = 80
"""How much of a malformed value or message an error quotes."""
_GRAPH_SPLITS = 6
"""``dbml/graph/<role>/<host>/<uid>/<variant>/<topic...>``: the topic keeps its slashes."""
_NODE_PARTS = 5
_FOLLOWS_ALL = "all"
_FOLLOWS_OWN = "own"
_OWN_PARTS = 4
_NODE_ID_HEX = 16
_NODE_ID = re.compile(rf"[0-9a-f]{{{_NODE_ID_HEX}}}")
_HOST_CHUNK = re.compile(r"[A-Za-z0-9_.~-]+")
"""A host name as ``dbml.transports.base.resolve_host`` allows them: one key chunk."""


def new_node_id() -> str:
    """A session's id on the wire: hex digits of a random UUID, unique per session."""
    return uuid.uuid4().hex[:_NODE_ID_HEX]


def is_node_id(text: str) -> bool:
    """Whether ``text`` is a session id as ``new_node_id`` makes them (a peer's is untrusted)."""
    return _NODE_ID.fullmatch(text) is not None


def data_key(topic: str) -> str:
    """The key a topic's messages travel under: the topic without its leading slash."""
    return check_topic(topic)[1:]


def is_host_name(text: str) -> bool:
    """Whether ``text`` is a host name: letters, digits and ``_-.~``, one key chunk."""
    return _HOST_CHUNK.fullmatch(text) is not None


def batch_key(host: str | None = None) -> str:
    """Where a batch travels: the one for every session, or the one for ``host``'s sessions.

    A round's values of the channels published on ``host`` go to ``dbml/batch/<host>``, so a
    robot hears its own channels' allocation and not the fleet's.
    """
    if host is None:
        return BATCH
    if not is_host_name(host):
        raise TransportError(f"host={short_repr(host)} is not a host name (letters, digits, _-.~)")
    return f"{BATCH}/{host}"


def param_key(name: str) -> str:
    """The key a parameter's writes are published under."""
    return PARAM + check_topic(name)


def global_params_filter() -> str:
    """The key expression of every global parameter's writes."""
    return f"{PARAM}{GLOBAL_PREFIX}/**"


def channel_params_filter(key: str) -> str | None:
    """The key expression of the channel parameters that ``key`` (a write's) belongs to.

    None for a global parameter or a key that is not a channel parameter's.
    """
    if not key.startswith(PARAM + "/"):
        return None
    split = split_channel_name(key[len(PARAM) :])
    return None if split is None else topic_params_filter(split[0])


def topic_params_filter(topic: str) -> str:
    """The key expression of every parameter of channel ``topic``."""
    return f"{param_key(topic)}{GLOBAL_PREFIX}/**"


def own_key(node_id: str, name: str = "") -> str:
    """Where session ``node_id`` serves ``name`` (all it owns with ``**`` after its prefix)."""
    return f"{OWN}/{node_id}{name}"


def own_name(key: str) -> tuple[str, str] | None:
    """``(node id, parameter name)`` of an owned value's key; None if malformed."""
    parts = key.split("/", _OWN_PARTS - 1)
    if len(parts) != _OWN_PARTS or f"{parts[0]}/{parts[1]}" != OWN or not parts[2]:
        return None
    return parts[2], "/" + parts[3]


def node_key(node_id: str, zid: str, *, follows_all: bool = True) -> str:
    """A session's liveliness token, saying whether it follows every parameter.

    A session that follows only its own channels' (a robot) needs no meeting with another such
    session: neither holds anything the other hears. Two robots of a fleet then never meet, and
    a fleet's start costs each robot a meeting with each session that follows everything, not
    with every robot (80 x 4 robots meeting each other delayed the optimizer's heartbeat by 6 s).
    """
    scope = _FOLLOWS_ALL if follows_all else _FOLLOWS_OWN
    return f"{NODE}/{node_id}/{zid}/{scope}"


def node_filter(*, follows_all: bool) -> str:
    """The session tokens a session hears: all of them if it follows every parameter.

    One that follows only its own channels (a robot) hears only the sessions that follow
    everything, the ones it meets: a robot's share of the fleet's tokens stays the same however
    many robots there are (at 80 x 4, 2.9 tokens a robot instead of 79).
    """
    return f"{NODE}/**" if follows_all else f"{NODE}/*/*/{_FOLLOWS_ALL}"


def parse_node_key(key: str) -> tuple[str, str, bool] | None:
    """``(node id, zenoh id, follows all)`` of a session token; None if malformed."""
    parts = key.split("/")
    if len(parts) != _NODE_PARTS or f"{parts[0]}/{parts[1]}" != NODE:
        return None
    if parts[4] not in (_FOLLOWS_ALL, _FOLLOWS_OWN):
        return None
    return parts[2], parts[3], parts[4] == _FOLLOWS_ALL


@dataclass(frozen=True, slots=True)
class GraphKey:
    """The fields of a graph declaration's token, as strings (the transport types them)."""

    role: str
    host: str
    uid: str
    variant: str
    topic: str


def graph_key(role: str, host: str, uid: str, variant: str, topic: str) -> str:
    """A declaration's liveliness token: ``host`` plays ``role`` on ``topic`` in ``variant``."""
    return f"{GRAPH}/{role}/{host}/{uid}/{variant}{check_topic(topic)}"


def topic_graph_filter(topic: str) -> str:
    """The key expression of every graph token on ``topic`` (whoever plays what there)."""
    return f"{GRAPH}/*/*/*/*{check_topic(topic)}"


def parse_graph_key(key: str) -> GraphKey | None:
    """The fields of a graph token; None if malformed."""
    parts = key.split("/", _GRAPH_SPLITS)
    if len(parts) <= _GRAPH_SPLITS or f"{parts[0]}/{parts[1]}" != GRAPH:
        return None
    return GraphKey(parts[2], parts[3], parts[4], parts[5], "/" + parts[6])


# -- parameter writes -------------------------------------------------------------------------


def encode_param(value: ParamValue, stamp_ns: int, writer: str) -> bytes:
    """Wire form of a parameter write: the value, when it was written and by whom."""
    check_param_value(value)
    return json.dumps({"v": value, "t": stamp_ns, "w": writer}).encode()


def encode_batch(values: Mapping[str, ParamValue], stamp_ns: int, writer: str) -> bytes:
    """Wire form of several writes with one stamp: ``{"vs": {name: value}, "t", "w"}``."""
    for name, value in values.items():
        check_topic(name)
        check_param_value(value)
    return json.dumps({"vs": dict(values), "t": stamp_ns, "w": writer}).encode()


def _malformed(data: bytes, what: str = "parameter write") -> TransportError:
    return TransportError(f"malformed {what} {data[:_SHOWN_CHARS]!r}")


def _scalar(value: object) -> ParamValue:
    try:
        return check_param_value(value)
    except TransportError:
        raise TransportError(f"malformed parameter value {short_repr(value)}") from None


def _document(data: bytes, what: str) -> dict[str, object]:
    if len(data) > MAX_WRITE_BYTES:
        raise TransportError(f"{what} of {len(data)} bytes (more than {MAX_WRITE_BYTES})")
    try:
        document = json.loads(data)
    except (ValueError, RecursionError) as err:
        raise _malformed(data, what) from err
    if not isinstance(document, dict):
        raise _malformed(data, what)
    return document


def _stamp_and_writer(document: dict[str, object], data: bytes, what: str) -> tuple[int, str]:
    stamp, writer = document.get("t"), document.get("w")
    if not isinstance(stamp, int) or isinstance(stamp, bool) or not isinstance(writer, str):
        raise _malformed(data, what)
    return stamp, writer


def decode_param(data: bytes) -> tuple[ParamValue, int, str]:
    """A write's value, stamp and writer; a malformed one raises ``TransportError``."""
    document = _document(data, "parameter write")
    if "v" not in document:
        raise _malformed(data)
    stamp, writer = _stamp_and_writer(document, data, "parameter write")
    return _scalar(document["v"]), stamp, writer


def decode_batch(data: bytes) -> tuple[dict[str, ParamValue], int, str]:
    """A batch's values by name, stamp and writer; a malformed one raises ``TransportError``."""
    document = _document(data, "batch")
    values = document.get("vs")
    if not isinstance(values, dict):
        raise _malformed(data, "batch")
    stamp, writer = _stamp_and_writer(document, data, "batch")
    checked = {check_topic(name): _scalar(value) for name, value in values.items()}
    return checked, stamp, writer
