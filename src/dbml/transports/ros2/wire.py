"""rmw_zenoh's wire formats, pure: type names and hashes, keys, attachments, liveliness tokens.

Everything here is a function of its arguments (no session, no thread, no clock), so each format
is tested against the examples rmw_zenoh's design documents and a real SDK produced. Message
types come from a ``rosbags`` typestore of one ROS 2 distro, plus the ``.msg`` files found under
``msg_paths`` (laid out as ``<dir>/<package>/msg/<Name>.msg``, as in a ROS workspace).

Formats (rmw_zenoh for zenoh 1.x, Humble to Rolling):

* data key ``<domain>/<topic without its leading slash>/<pkg>::msg::dds_::<Name>_/RIHS01_<hex>``;
* attachment, 33 bytes little-endian: int64 sequence (from 1), int64 source time in ns since the
  epoch, the byte ``0x10`` and a 16-byte publisher GID;
* liveliness tokens ``@ros2_lv/<domain>/<zid>/<nid>/<eid>/<kind>/<enclave>/<ns>/<node>`` and,
  for endpoints, ``/<topic>/<dds type>/<hash>/<qos>``, with every ``/`` in a name written ``%``.
"""

from __future__ import annotations

import enum
import re
import struct
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from dbml.core.errors import TransportError
from dbml.core.extras import require

if TYPE_CHECKING:  # rosbags (the ros2 extra) loads when a transport resolves types
    from rosbags.typesys.store import Typestore

__all__ = [
    "ADMIN_SPACE",
    "ATTACHMENT_SIZE_BYTES",
    "DEFAULT_DISTRO",
    "DISTROS",
    "MAX_DOMAIN_ID",
    "QOS_RELIABLE_VOLATILE_KEEP_LAST_10",
    "Attachment",
    "LivelinessToken",
    "MessageTypes",
    "TokenKind",
    "check_domain_id",
    "data_key",
    "dds_type_name",
    "decode_attachment",
    "encode_attachment",
    "mangle",
    "parse_token",
    "ros_type_name",
    "unmangle",
]

DISTROS = ("jazzy", "kilted", "lyrical")
"""The ROS 2 distros whose typestores ``rosbags`` ships and whose rmw_zenoh hashes types."""
DEFAULT_DISTRO = "jazzy"
_STORES = {"jazzy": "ros2_jazzy", "kilted": "ros2_kilted", "lyrical": "ros2_lyrical"}
"""Each distro's ``rosbags.typesys.Stores`` value."""
MAX_DOMAIN_ID = 232
"""The largest ROS 2 domain id (as ``ROS_DOMAIN_ID`` allows)."""
ADMIN_SPACE = "@ros2_lv"
"""rmw_zenoh's liveliness prefix; ``@`` keeps ``**`` of other keys from matching it."""
QOS_RELIABLE_VOLATILE_KEEP_LAST_10 = "1:2:1,10:,:,:,,"
"""Explicit, not left to defaults: rmw_zenoh's default durability changed in 2025."""

ATTACHMENT_SIZE_BYTES = 33
GID_SIZE_BYTES = 16
_ATTACHMENT = struct.Struct("<qqB")
_NODE_CHUNKS = 9
_ENDPOINT_CHUNKS = 13
_MAX_ZID_HEX = 32

_TYPE = re.compile(r"([A-Za-z][A-Za-z0-9_]*)/(msg|srv)/([A-Za-z][A-Za-z0-9_]*)")
_DDS_TYPE = re.compile(r"([A-Za-z][A-Za-z0-9_]*)::(msg|srv)::dds_::([A-Za-z][A-Za-z0-9_]*)_")
_HASH = re.compile(r"RIHS01_[0-9a-f]{64}|TypeHashNotSupported")
_ZID = re.compile(r"[0-9a-f]{1,32}")
_DECIMAL = re.compile(r"[0-9]{1,20}")
_NAME_CHUNK = re.compile(r"%|(%[A-Za-z0-9_~.\-]+)+")
"""A mangled enclave, namespace or topic: ``%`` alone, or ``%seg%seg``."""
_QOS = re.compile(r"\d*:\d*:\d*,\d*:\d*,\d*:\d*,\d*:\d*,\d*,\d*")
"""``rel:dur:hist,depth:deadline s,ns:lifespan s,ns:liveliness,lease s,ns``; empty is default."""
_NODE_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def check_domain_id(value: object) -> int:
    """``value`` as a ROS 2 domain id, 0..232; ``TransportError`` names anything else."""
    try:
        domain = int(str(value).strip()) if not isinstance(value, int) else value
    except ValueError:
        domain = -1
    if isinstance(value, bool) or not 0 <= domain <= MAX_DOMAIN_ID:
        raise TransportError(f"ros domain id {value!r} must be an integer 0..{MAX_DOMAIN_ID}")
    return domain


def mangle(name: str) -> str:
    """A name as one key chunk: every ``/`` becomes ``%``, as rmw_zenoh writes it."""
    return name.replace("/", "%")


def unmangle(chunk: str) -> str:
    """The name a mangled key chunk stands for."""
    return chunk.replace("%", "/")


def dds_type_name(msg_type: str) -> str:
    """``sensor_msgs/msg/Image`` as rmw_zenoh's keys name it: ``sensor_msgs::msg::dds_::Image_``."""
    match = _TYPE.fullmatch(msg_type)
    if match is None:
        raise TransportError(f"message type {msg_type!r} must look like 'pkg/msg/Name'")
    package, kind, name = match.groups()
    return f"{package}::{kind}::dds_::{name}_"


def ros_type_name(dds_type: str) -> str:
    """The inverse of ``dds_type_name``."""
    match = _DDS_TYPE.fullmatch(dds_type)
    if match is None:
        raise TransportError(f"dds type {dds_type!r} must look like 'pkg::msg::dds_::Name_'")
    package, kind, name = match.groups()
    return f"{package}/{kind}/{name}"


def data_key(domain_id: int, topic: str, msg_type: str, type_hash: str) -> str:
    """The key every message of ``topic`` travels under; rmw subscribes to exactly this key."""
    name = topic.removeprefix("/").removesuffix("/")
    return f"{domain_id}/{name}/{dds_type_name(msg_type)}/{type_hash}"


@dataclass(frozen=True, slots=True)
class Attachment:
    """What rmw_zenoh attaches to every message; its subscribers drop a message without one."""

    sequence: int
    """Per publisher, from 1."""
    timestamp_ns: int
    """Source time, ns since the epoch."""
    gid: bytes
    """The publisher's 16-byte id."""


def encode_attachment(attachment: Attachment) -> bytes:
    """The 33 bytes rmw_zenoh parses (zenoh-ext serialisation of int64, int64, byte[16])."""
    if len(attachment.gid) != GID_SIZE_BYTES:
        raise TransportError(f"gid of {len(attachment.gid)} bytes must be {GID_SIZE_BYTES}")
    head = _ATTACHMENT.pack(attachment.sequence, attachment.timestamp_ns, GID_SIZE_BYTES)
    return head + attachment.gid


def decode_attachment(data: bytes) -> Attachment:
    """The attachment in ``data``; ``TransportError`` if it is not rmw_zenoh's 33 bytes."""
    if len(data) != ATTACHMENT_SIZE_BYTES:
        raise TransportError(
            f"rmw attachment of {len(data)} bytes must be {ATTACHMENT_SIZE_BYTES} bytes"
        )
    sequence, timestamp_ns, gid_size = _ATTACHMENT.unpack_from(data)
    if gid_size != GID_SIZE_BYTES:
        raise TransportError(f"rmw attachment gid length {gid_size} must be {GID_SIZE_BYTES}")
    return Attachment(sequence, timestamp_ns, bytes(data[_ATTACHMENT.size :]))


class TokenKind(enum.StrEnum):
    """What a liveliness token declares."""

    NODE = "NN"
    PUBLISHER = "MP"
    SUBSCRIPTION = "MS"
    SERVICE = "SS"
    CLIENT = "SC"


@dataclass(frozen=True, slots=True)
class LivelinessToken:
    """One rmw_zenoh graph declaration: a node, or one endpoint of a node."""

    domain_id: int
    zid: str
    """The zenoh session's id, as ``str(session.info.zid())`` prints it."""
    node_id: int
    entity_id: int
    kind: TokenKind
    node_name: str
    namespace: str = "/"
    enclave: str = "/"
    topic: str | None = None
    """Endpoints only: the fully qualified topic (``/r1/camera``)."""
    msg_type: str | None = None
    """Endpoints only: ``pkg/msg/Name``."""
    type_hash: str | None = None
    qos: str | None = None

    def key(self) -> str:
        """The token's key expression."""
        head = (
            f"{ADMIN_SPACE}/{self.domain_id}/{self.zid}/{self.node_id}/{self.entity_id}/"
            f"{self.kind.value}/{mangle(self.enclave)}/{mangle(self.namespace)}/{self.node_name}"
        )
        if self.kind is TokenKind.NODE:
            return head
        if self.topic is None or self.msg_type is None or not self.type_hash or not self.qos:
            raise TransportError(f"{self.kind.value} token needs a topic, type, hash and qos")
        return (
            f"{head}/{mangle(self.topic)}/{dds_type_name(self.msg_type)}/"
            f"{self.type_hash}/{self.qos}"
        )


def _reject(key: str, why: str) -> TransportError:
    return TransportError(f"liveliness token {key[:160]!r}: {why}")


def parse_token(key: str) -> LivelinessToken:
    """The token a liveliness key declares; ``TransportError`` saying why a key is malformed.

    Keys come from the network: every chunk is checked (count, kinds, ids, names, type, hash).
    """
    chunks = key.split("/")
    if chunks[0] != ADMIN_SPACE:
        raise _reject(key, f"does not start with {ADMIN_SPACE}")
    if len(chunks) not in {_NODE_CHUNKS, _ENDPOINT_CHUNKS} or not all(chunks):
        raise _reject(key, f"has {len(chunks)} chunks or an empty one")
    _, domain, zid, node_id, entity_id, kind_chunk, enclave, namespace, node_name = chunks[:9]
    try:
        kind = TokenKind(kind_chunk)
    except ValueError:
        raise _reject(key, f"kind {kind_chunk!r} is not one of NN, MP, MS, SS, SC") from None
    if (kind is TokenKind.NODE) != (len(chunks) == _NODE_CHUNKS):
        raise _reject(key, f"kind {kind.value} with {len(chunks)} chunks")
    for label, chunk in (("domain", domain), ("node id", node_id), ("entity id", entity_id)):
        if not _DECIMAL.fullmatch(chunk):
            raise _reject(key, f"{label} {chunk!r} is not a decimal number")
    if not _ZID.fullmatch(zid) or len(zid) > _MAX_ZID_HEX:
        raise _reject(key, f"zid {zid!r} is not a zenoh id")
    if int(domain) > MAX_DOMAIN_ID:
        raise _reject(key, f"domain {domain} is above {MAX_DOMAIN_ID}")
    for label, chunk in (("enclave", enclave), ("namespace", namespace)):
        if not _NAME_CHUNK.fullmatch(chunk):
            raise _reject(key, f"{label} {chunk!r} is not a mangled name")
    if not _NODE_NAME.fullmatch(node_name):
        raise _reject(key, f"node name {node_name!r} is not a ROS name")
    token = LivelinessToken(
        int(domain),
        zid,
        int(node_id),
        int(entity_id),
        kind,
        node_name,
        unmangle(namespace),
        unmangle(enclave),
    )
    if kind is TokenKind.NODE:
        return token
    topic, dds_type, type_hash, qos = chunks[9:]
    if topic == "%" or not _NAME_CHUNK.fullmatch(topic):
        raise _reject(key, f"topic {topic!r} is not a mangled topic name")
    try:
        msg_type = ros_type_name(dds_type)
    except TransportError as err:
        raise _reject(key, str(err)) from None
    if not _HASH.fullmatch(type_hash):
        raise _reject(key, f"type hash {type_hash[:80]!r} is not RIHS01_<64 hex>")
    if not _QOS.fullmatch(qos):
        raise _reject(key, f"qos {qos[:80]!r} is not rmw_zenoh's qos format")
    return LivelinessToken(
        token.domain_id,
        zid,
        token.node_id,
        token.entity_id,
        kind,
        node_name,
        token.namespace,
        token.enclave,
        unmangle(topic),
        msg_type,
        type_hash,
        qos,
    )


def _msg_files(msg_paths: Iterable[str | Path]) -> dict[str, Path]:
    found: dict[str, Path] = {}
    for root in msg_paths:
        directory = Path(root)
        if not directory.is_dir():
            raise TransportError(f"msg path {str(root)!r} is not a directory")
        for path in sorted(directory.rglob("*.msg")):
            if path.parent.name == "msg":
                found[f"{path.parent.parent.name}/msg/{path.stem}"] = path
    return found


class MessageTypes:
    """The message types one transport knows: a distro's typestore plus ``.msg`` files.

    Resolving a type also computes its RIHS01 hash, so a type whose definition or dependencies
    are missing is refused before any key is built from it.
    """

    def __init__(self, *, distro: str | None = None, msg_paths: Sequence[str | Path] = ()) -> None:
        self.distro = DEFAULT_DISTRO if distro is None else distro
        store = _STORES.get(self.distro)
        if store is None:
            raise TransportError(f"ros distro {self.distro!r} is not one of: {', '.join(DISTROS)}")
        require("rosbags", extra="ros2", what="transport 'ros2'")
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        self._store: Typestore = get_typestore(Stores(store))
        files = _msg_files(msg_paths)
        for name, path in files.items():
            # One file at a time, so a clash with the typestore names the file and its type.
            try:
                self._store.register(get_types_from_msg(path.read_text(encoding="utf-8"), name))
            except Exception as err:  # rosbags raises its own parser and type-system errors
                raise TransportError(f"msg file {str(path)!r} (type {name!r}): {err}") from err
        self._hashes: dict[str, str] = {}

    def type_hash(self, msg_type: str) -> str:
        """The RIHS01 hash of ``msg_type``; ``TransportError`` naming a type not known."""
        known = self._hashes.get(msg_type)
        if known is not None:
            return known
        dds_type_name(msg_type)  # the name's shape, first
        if msg_type not in self._store.types:
            raise TransportError(
                f"message type {msg_type!r} is not known to the {self.distro} typestore"
                " or --msg-path"
            )
        try:
            digest = self._store.hash_rihs01(msg_type)
        except Exception as err:  # a custom type with a missing dependency
            raise TransportError(f"message type {msg_type!r} cannot be hashed: {err}") from err
        self._hashes[msg_type] = digest
        return digest

    def definition(self, msg_type: str) -> str:
        """The ``.msg`` text of ``msg_type`` with its dependencies, as ROS 2 tools print it."""
        self.type_hash(msg_type)
        try:
            text, _ = self._store.generate_msgdef(msg_type, ros_version=2)
        except Exception as err:  # a custom type whose definition rosbags cannot render
            raise TransportError(f"message type {msg_type!r} has no definition: {err}") from err
        return text

    @property
    def store(self) -> Typestore:
        """The ``rosbags`` typestore (for tests and peers that (de)serialise messages)."""
        return self._store
