"""rmw_zenoh's formats against the examples its design document and a real SDK produced."""

from __future__ import annotations

from pathlib import Path

import pytest

from dbml.core.errors import TransportError
from dbml.transports.codecs import FLOAT64_TYPE, IMAGE_TYPE
from dbml.transports.ros2.wire import (
    ATTACHMENT_SIZE_BYTES,
    DISTROS,
    QOS_RELIABLE_VOLATILE_KEEP_LAST_10,
    Attachment,
    LivelinessToken,
    MessageTypes,
    TokenKind,
    check_domain_id,
    data_key,
    dds_type_name,
    decode_attachment,
    encode_attachment,
    mangle,
    parse_token,
    ros_type_name,
    unmangle,
)

STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
IMAGE_HASH = "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47"
FLOAT64_HASH = "RIHS01_705ba9c3d1a09df43737eb67095534de36fd426c0587779bda2bc51fe790182a"
SDK_MP = (
    "@ros2_lv/0/6e100baa5e8bca85ecd30790986d1fbd/0/0/MP/%/%/sdk_talker/%chatter/"
    f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,10:,:,:,,"
)
"""A token the SDK declared (spec section 3.1)."""
OUR_MP = (
    "@ros2_lv/0/1ae02cbf9ef3ea883e34c72fcf83f1a7/0/1/MP/%/%/dbml_cam/%camera%image_raw/"
    f"sensor_msgs::msg::dds_::Image_/{IMAGE_HASH}/1:2:1,10:,:,:,,"
)


@pytest.fixture(scope="module")
def types() -> MessageTypes:
    return MessageTypes()


def test_data_key_matches_rmw_zenoh_design_example(types: MessageTypes) -> None:
    msg_type = "std_msgs/msg/String"
    assert data_key(0, "/robot1/chatter", msg_type, types.type_hash(msg_type)) == (
        f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    )
    assert data_key(7, "/chatter/", msg_type, "h").startswith("7/chatter/std_msgs")


@pytest.mark.parametrize("distro", DISTROS)
def test_common_hashes_are_the_same_in_every_distro(distro: str) -> None:
    types = MessageTypes(distro=distro)
    assert types.type_hash(IMAGE_TYPE) == IMAGE_HASH
    assert types.type_hash(FLOAT64_TYPE) == FLOAT64_HASH


def test_unknown_distro_and_type_are_named(types: MessageTypes) -> None:
    with pytest.raises(TransportError, match="ros distro 'foxy' is not one of: jazzy, kilted"):
        MessageTypes(distro="foxy")
    with pytest.raises(TransportError, match=r"'foo/msg/Bar' is not known to the jazzy typestore"):
        types.type_hash("foo/msg/Bar")
    with pytest.raises(TransportError, match=r"'Image' must look like 'pkg/msg/Name'"):
        types.type_hash("Image")


def test_custom_types_come_from_msg_paths(tmp_path: Path) -> None:
    package = tmp_path / "dbml_msgs" / "msg"
    package.mkdir(parents=True)
    (package / "Probe.msg").write_text("uint32 seq\nfloat64[] values\nstring label\n")
    types = MessageTypes(msg_paths=[tmp_path])
    assert types.type_hash("dbml_msgs/msg/Probe") == (
        "RIHS01_a5f08f66d9c266bbeb1b26d9bc60952bb81d9cfd93c0dba0cc01f95e34851a02"
    )
    with pytest.raises(TransportError, match=r"msg path '.*nowhere' is not a directory"):
        MessageTypes(msg_paths=[tmp_path / "nowhere"])


def test_custom_types_may_use_each_other(tmp_path: Path) -> None:
    package = tmp_path / "dbml_msgs" / "msg"
    package.mkdir(parents=True)
    (package / "Outer.msg").write_text("dbml_msgs/Inner inner\n")  # sorted before its dependency
    (package / "Inner.msg").write_text("uint32 seq\n")
    assert MessageTypes(msg_paths=[tmp_path]).type_hash("dbml_msgs/msg/Outer").startswith("RIHS01_")


def test_a_msg_file_clashing_with_the_typestore_is_a_transport_error(tmp_path: Path) -> None:
    package = tmp_path / "std_msgs" / "msg"
    package.mkdir(parents=True)
    (package / "String.msg").write_text("int32 data\n")  # the typestore's says string data
    with pytest.raises(
        TransportError, match=r"msg file '.*String\.msg' \(type 'std_msgs/msg/String'\): "
    ) as raised:
        MessageTypes(msg_paths=[tmp_path])
    assert raised.value.__cause__ is not None


def test_dds_type_names_round_trip() -> None:
    assert dds_type_name(IMAGE_TYPE) == "sensor_msgs::msg::dds_::Image_"
    assert ros_type_name("sensor_msgs::msg::dds_::Image_") == IMAGE_TYPE
    with pytest.raises(TransportError, match="dds type 'Image' must look like"):
        ros_type_name("Image")


def test_mangling_replaces_slashes_only() -> None:
    assert mangle("/camera/image_raw") == "%camera%image_raw"
    assert unmangle("%camera%image_raw") == "/camera/image_raw"


@pytest.mark.parametrize("value", [0, 232, "5"])
def test_domain_ids_in_range(value: object) -> None:
    assert check_domain_id(value) == int(str(value))


@pytest.mark.parametrize("value", [-1, 233, "x", True, 1.5])
def test_domain_ids_out_of_range_are_named(value: object) -> None:
    with pytest.raises(TransportError, match=r"ros domain id .* must be an integer 0\.\.232"):
        check_domain_id(value)


def test_attachment_layout_is_rmw_zenohs() -> None:
    gid = bytes(range(16))
    data = encode_attachment(Attachment(1, 0x17979CFE3D85CD15, gid))
    assert len(data) == ATTACHMENT_SIZE_BYTES
    assert data.hex() == "010000000000000015cd853dfe9c971710000102030405060708090a0b0c0d0e0f"
    assert decode_attachment(data) == Attachment(1, 0x17979CFE3D85CD15, gid)


def test_sdk_attachment_decodes() -> None:
    sdk = bytes.fromhex("000000000000000000bca0370ebcea1810794cf165a61843c2bdcd52bc87358d37")
    decoded = decode_attachment(sdk)
    assert (decoded.sequence, decoded.timestamp_ns) == (0, 1795454170709408768)
    assert decoded.gid.hex() == "794cf165a61843c2bdcd52bc87358d37"


def test_malformed_attachments_are_refused() -> None:
    with pytest.raises(TransportError, match="of 32 bytes must be 33 bytes"):
        decode_attachment(bytes(32))
    with pytest.raises(TransportError, match="gid length 15 must be 16"):
        decode_attachment(bytes(16) + b"\x0f" + bytes(16))
    with pytest.raises(TransportError, match="gid of 3 bytes must be 16"):
        encode_attachment(Attachment(1, 2, b"abc"))


def test_tokens_round_trip() -> None:
    for key in (SDK_MP, OUR_MP):
        assert parse_token(key).key() == key
    token = parse_token(OUR_MP)
    assert (token.kind, token.topic, token.msg_type) == (
        TokenKind.PUBLISHER,
        "/camera/image_raw",
        IMAGE_TYPE,
    )
    node = LivelinessToken(3, "abcd", 0, 0, TokenKind.NODE, "dbml_host_a")
    assert node.key() == "@ros2_lv/3/abcd/0/0/NN/%/%/dbml_host_a"
    assert parse_token(node.key()) == node
    subscription = LivelinessToken(
        0,
        "abcd",
        0,
        4,
        TokenKind.SUBSCRIPTION,
        "dbml_a",
        namespace="/ns",
        topic="/r1/camera/optimized",
        msg_type=IMAGE_TYPE,
        type_hash=IMAGE_HASH,
        qos=QOS_RELIABLE_VOLATILE_KEEP_LAST_10,
    )
    assert subscription.key().split("/")[7:10] == ["%ns", "dbml_a", "%r1%camera%optimized"]
    assert parse_token(subscription.key()) == subscription


@pytest.mark.parametrize(
    ("key", "why"),
    [
        ("@ros2_lv/0/abcd/0/0/NN/%/%", "has 8 chunks"),
        ("dbml/0/abcd/0/0/NN/%/%/n", "does not start with @ros2_lv"),
        ("@ros2_lv/0/abcd/0/0/XX/%/%/n", "kind 'XX' is not one of"),
        ("@ros2_lv/0/abcd/0/0/MP/%/%/n", "kind MP with 9 chunks"),
        ("@ros2_lv/0/ABCD/0/0/NN/%/%/n", "zid 'ABCD' is not a zenoh id"),
        ("@ros2_lv/999/abcd/0/0/NN/%/%/n", "domain 999 is above 232"),
        ("@ros2_lv/0/abcd/x/0/NN/%/%/n", "node id 'x' is not a decimal number"),
        ("@ros2_lv/0/abcd/0/0/NN/%/ns/n", "namespace 'ns' is not a mangled name"),
        ("@ros2_lv/0/abcd/0/0/NN/%/%/9n", "node name '9n' is not a ROS name"),
        (SDK_MP.replace("String_", "String"), "dds type .* must look like"),
        (SDK_MP.replace(STRING_HASH, "RIHS01_zz"), "type hash 'RIHS01_zz' is not"),
        (SDK_MP.replace("::,10:,:,:,,", "bad"), "qos 'bad' is not rmw_zenoh's qos format"),
        (SDK_MP.replace("%chatter", "%"), "topic '%' is not a mangled topic name"),
    ],
)
def test_malformed_tokens_are_rejected_with_the_reason(key: str, why: str) -> None:
    with pytest.raises(TransportError, match=why):
        parse_token(key)


def test_endpoint_tokens_need_their_fields() -> None:
    with pytest.raises(TransportError, match="MS token needs a topic, type, hash and qos"):
        LivelinessToken(0, "abcd", 0, 1, TokenKind.SUBSCRIPTION, "n").key()
