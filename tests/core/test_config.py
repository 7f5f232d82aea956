import textwrap
from pathlib import Path

import pytest

from dbml.core import ConfigError, Strategy, parse_config
from dbml.core.config import load_config, parse_bridge_channels

VALID = """
dbm:
  max_bandwidth_in_mbit: 11
  max_bandwidth_utilization: 0.9
  optimization_rate_in_seconds: 0.5
  strategy: lp
channels:
  - topic: /r1/camera
    frequency: {min: 1, max: 16}
    message_size_in_bytes: 84000
    priority: 0.25
  - topic: /r2/camera
    frequency: {min: 2, max: 8}
    message_size_in_bytes: 21000
links:
  - {name: r1-uplink, max_bandwidth_in_mbit: 6, channels: [/r1/camera]}
"""


def test_parses_every_field() -> None:
    config = parse_config(VALID)
    assert config.dbm.max_bandwidth_mbit == 11.0
    assert config.dbm.utilization == 0.9
    assert config.dbm.optimization_period_s == 0.5
    assert config.dbm.strategy is Strategy.LP
    first, second = config.channels
    assert (first.topic, first.min_rate_hz, first.max_rate_hz) == ("/r1/camera", 1.0, 16.0)
    assert (first.size_bytes, first.priority) == (84_000.0, 0.25)
    assert second.priority == 0.0
    assert config.links[0].name == "r1-uplink"
    assert config.links[0].capacity_mbit == 6.0
    assert config.links[0].topics == ("/r1/camera",)
    problem = config.problem()
    assert problem.budget_bytes_per_s == pytest.approx(11 * 125_000 * 0.9)


def test_defaults() -> None:
    config = parse_config(
        "dbm: {max_bandwidth_in_mbit: 2}\n"
        "channels: [{topic: /a, frequency: {min: 1, max: 2}, message_size_in_bytes: 10}]"
    )
    assert config.dbm.utilization == 1.0
    assert config.dbm.optimization_period_s == 1.0
    assert config.dbm.strategy is Strategy.PAPER
    assert config.links == ()


def test_dbm_only_config_is_valid_when_channels_come_live() -> None:
    config = parse_config("dbm: {max_bandwidth_in_mbit: 2}", require_channels=False)
    assert config.channels == ()
    with pytest.raises(ConfigError, match=r"channels is missing or empty"):
        parse_config("dbm: {max_bandwidth_in_mbit: 2}")
    with pytest.raises(ConfigError, match=r"config: channels is empty"):
        config.problem()


def replace(old: str, new: str) -> str:
    assert old in VALID
    return VALID.replace(old, new)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            replace("    priority: 0.25", "    priorty: 0.25"),
            r"channels\[0\] '/r1/camera': unknown key 'priorty'",
        ),
        (
            replace("  strategy: lp", "  strategy: magic"),
            r"dbm: strategy='magic' is not one of paper",
        ),
        (
            replace("max_bandwidth_in_mbit: 11", "max_bandwidth_in_mbit: 0"),
            r"dbm: max_bandwidth_in_mbit=0 must be > 0",
        ),
        (
            replace("max_bandwidth_in_mbit: 11", "max_bandwidth_in_mbit: eleven"),
            r"dbm: max_bandwidth_in_mbit='eleven' is not a number",
        ),
        (
            replace("utilization: 0.9", "utilization: 1.5"),
            r"dbm: max_bandwidth_utilization=1.5 must be within \(0, 1\]",
        ),
        (
            replace("optimization_rate_in_seconds: 0.5", "optimization_rate_in_seconds: -1"),
            r"dbm: optimization_rate_in_seconds=-1 must be > 0",
        ),
        (
            replace("{min: 1, max: 16}", "{min: 30, max: 16}"),
            r"channels\[0\] channel '/r1/camera': frequency.min=30.0 exceeds frequency.max=16.0",
        ),
        (
            replace("{min: 1, max: 16}", "{min: 0, max: 16}"),
            r"channels\[0\] channel '/r1/camera': frequency.min=0.0 must be > 0",
        ),
        (
            replace("{min: 1, max: 16}", "{min: 1}"),
            r"channels\[0\] '/r1/camera': frequency: missing required key 'max'",
        ),
        (
            replace("{min: 1, max: 16}", "{min: 1, max: 16, avg: 3}"),
            r"frequency: unknown key 'avg'",
        ),
        (
            replace("message_size_in_bytes: 84000", "message_size_in_bytes: -5"),
            r"channel '/r1/camera': message_size_in_bytes=-5.0 must be > 0",
        ),
        (
            replace("message_size_in_bytes: 21000", "message_size_in_bytes: true"),
            r"channels\[1\] '/r2/camera': message_size_in_bytes=True is not a number",
        ),
        (
            replace("priority: 0.25", "priority: 2"),
            r"channel '/r1/camera': priority=2.0 must be within \[0, 1\]",
        ),
        (
            replace("topic: /r2/camera", "topic: /r1/camera"),
            r"channels\[1\] '/r1/camera': topic is declared twice",
        ),
        (
            replace("topic: /r2/camera", "topic: r2/camera"),
            r"channels\[1\] 'r2/camera': topic='r2/camera' must be a string starting with '/'",
        ),
        (
            replace("    message_size_in_bytes: 21000\n", ""),
            r"channels\[1\] '/r2/camera': missing required key 'message_size_in_bytes'",
        ),
        (
            replace("channels: [/r1/camera]", "channels: [/r9/camera]"),
            r"links\[0\] 'r1-uplink': channels lists unknown topic '/r9/camera'",
        ),
        (
            replace("max_bandwidth_in_mbit: 6", "max_bandwidth_in_mbit: 0"),
            r"links\[0\] link 'r1-uplink': max_bandwidth_in_mbit=0.0 must be > 0",
        ),
        (
            replace("  strategy: lp", "  strategy: paper"),
            r"links\[0\] 'r1-uplink': links need strategy 'lp', but dbm.strategy='paper'",
        ),
        (replace("dbm:", "dbx:"), r"<config>: unknown key 'dbx'"),
        ("- just\n- a list\n", r"<config>: expected a mapping, got \['just', 'a list'\]"),
        (
            "dbm: {max_bandwidth_in_mbit: 2}\nchannels: {topic: /a}\n",
            r"<config>: channels=\{'topic': '/a'\} must be a list",
        ),
        ("dbm: [1, 2\n", r"<config>: invalid YAML at line 2"),
    ],
)
def test_validation_errors_name_field_and_value(text: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        parse_config(text)


def test_error_source_names_the_file() -> None:
    with pytest.raises(ConfigError, match=r"^config 'x.yaml': missing required key 'dbm'"):
        parse_config(textwrap.dedent("channels: []"), source="config 'x.yaml'")


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            "a: &a [1, 2]\nb: [*a, *a]\ndbm: {max_bandwidth_in_mbit: 11}\n",
            r"^<config>: YAML aliases \(\*a\) are not allowed$",
        ),
        ("dbm: " + "[" * 50_000 + "]" * 50_000 + "\n", r"^<config>: nested deeper than 16 levels$"),
        (
            "dbm:\n  max_bandwidth_in_mbit: 11\n  max_bandwidth_in_mbit: 5\n",
            r"invalid YAML at line 3, column 3: key 'max_bandwidth_in_mbit' is given twice$",
        ),
        (
            "dbm: {max_bandwidth_in_mbit: 1" + "0" * 400 + "}\n",
            r"^dbm: max_bandwidth_in_mbit=1000+\.\.\. is not finite$",
        ),
        (
            "dbm: {max_bandwidth_in_mbit: 11, optimization_rate_in_seconds: 0.001}\n",
            r"optimization_rate_in_seconds=0.001 must be within \[0.01, 3600\]$",
        ),
    ],
)
def test_hostile_yaml_is_one_error_not_a_hang_or_a_traceback(text: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        parse_config(text, require_channels=False)


def test_an_oversized_or_endless_file_is_refused_unread(tmp_path: Path) -> None:
    big = tmp_path / "big.yaml"
    big.write_text("#" * (2 << 20))
    with pytest.raises(ConfigError, match=r"big.yaml': larger than 1,048,576 bytes$"):
        load_config(big)
    with pytest.raises(ConfigError, match=r"^config '/dev/zero': larger than 1,048,576 bytes$"):
        load_config("/dev/zero")


def test_frame_headroom_is_read_and_checked() -> None:
    text = "dbm: {max_bandwidth_in_mbit: 11, frame_headroom: true}\nchannels: []\n"
    assert parse_config(text, require_channels=False).dbm.frame_headroom is True
    with pytest.raises(ConfigError, match=r"dbm: frame_headroom='yes' must be true or false"):
        parse_config(
            "dbm: {max_bandwidth_in_mbit: 11, frame_headroom: 'yes'}\nchannels: []\n",
            require_channels=False,
        )


def test_a_laddered_bridge_channel_is_an_image_and_says_so_otherwise() -> None:
    base = "channels:\n  - topic: /r1/camera\n    frequency: {min: 1, max: 16}\n"
    (channel,) = parse_bridge_channels(base + "    ladder: true\n")
    assert channel.ladder is True
    assert channel.msg_type == "sensor_msgs/msg/Image"
    with pytest.raises(ConfigError, match=r"^channels\[0\] '/r1/camera': ladder='yes' must be"):
        parse_bridge_channels(base + '    ladder: "yes"\n')
    with pytest.raises(ConfigError, match="type='std_msgs/msg/String' cannot be laddered"):
        parse_bridge_channels(base + "    ladder: true\n    type: std_msgs/msg/String\n")
