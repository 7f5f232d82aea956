"""``dbml bridge`` and ``dbml router``: bad command lines give one line and exit 2."""

import re
from pathlib import Path

import pytest

from dbml.cli.main import main
from dbml.core.config import BridgeChannel, parse_bridge_channels
from dbml.core.errors import ConfigError


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["bridge"], r"topic=None: give TOPIC"),
        (["bridge", "/r1/camera", "--max-hz", "16"], r"--min-hz=None: required"),
        (
            ["bridge", "/r1/camera", "--min-hz", "30", "--max-hz", "16"],
            r"frequency.min=30.0 exceeds frequency.max=16.0",
        ),
        (
            ["bridge", "/r1/camera", "--min-hz", "1", "--max-hz", "16", "--type", "Image"],
            r"type='Image' must look like 'sensor_msgs/msg/Image'",
        ),
        (["bridge", "/r1/camera", "--config", "x.yaml"], r"--config='x.yaml' and topic="),
        (["router", "--listen", "tcp/nonsense"], r"endpoint='tcp/nonsense'"),
        (
            ["bridge", "/a", "--min-hz", "1", "--max-hz", "2", "--ros-args", "-r", "__ns:=/r1"],
            r"--ros-args \(--ros-args -r __ns:=/r1\): only a node's command over --transport "
            r"rclpy takes them",
        ),
        (["reproduce", "table2", "--ros-args", "-p", "a:=1"], r"only a node.s command over"),
        (
            ["bridge", "--transport", "rclpy", "--ros-args", "-r", "__ns:=/r9"],
            r"no channel under namespace='/r9' with frequency.min and frequency.max",
        ),
    ],
)
def test_bad_command_lines_exit_2_with_one_line(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert err.startswith("dbml: error: ")
    assert re.search(message, err), err


def test_bridge_config_file_errors_name_the_field(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "bridge.yaml"
    path.write_text("channels:\n  - {topic: /a, frequency: {min: 1, max: 0}}\n")
    assert main(["bridge", "--config", str(path)]) == 2
    assert "channels[0] '/a': channel '/a': frequency.min=1.0 exceeds" in capsys.readouterr().err


def test_parse_bridge_channels() -> None:
    text = (
        "dbm: {max_bandwidth_in_mbit: 11}\n"
        "channels:\n"
        "  - {topic: /r1/camera, frequency: {min: 1, max: 16}, type: sensor_msgs/msg/Image}\n"
        "  - {topic: /r1/scan, frequency: {min: 2, max: 10}, priority: 0.5,"
        " message_size_in_bytes: 1000}\n"
    )
    assert parse_bridge_channels(text) == (
        BridgeChannel("/r1/camera", 1.0, 16.0, None, "sensor_msgs/msg/Image"),
        BridgeChannel("/r1/scan", 2.0, 10.0, 0.5, None),
    )


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("channels: []\n", r"channels=\[\] must be a non-empty list"),
        (
            "channels:\n  - {topic: /a, frequency: {min: 1, max: 2}}\n"
            "  - {topic: /a, frequency: {min: 1, max: 2}}\n",
            r"channels\[1\] '/a': topic is declared twice",
        ),
        ("channels:\n  - {topic: /a, topic: /b}\n", r"key 'topic' is given twice"),
        ("a: &x [1]\nchannels: *x\n", r"YAML aliases \(\*x\) are not allowed"),
        (
            "channels:\n  - {topic: /a, frequency: {min: 1, max: 2}, type: 3}\n",
            r"channels\[0\] '/a': type=3 must look like",
        ),
        (
            "channels:\n  - {topic: /a, frequency: {min: 1, max: 2}, colour: red}\n",
            r"unknown key 'colour'",
        ),
    ],
)
def test_parse_bridge_channels_rejects(text: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        parse_bridge_channels(text)


def test_a_bridge_over_rclpy_takes_its_namespaces_channels_from_a_params_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Checked before any network opens: a bad value exits 2 naming it."""
    path = tmp_path / "teleop.yaml"
    path.write_text("/r1/camera/dbm:\n  ros__parameters:\n    frequency: {min: 1.0, max: 0.5}\n")
    argv = ["bridge", "--transport", "rclpy", "--ros-args", "--params-file", str(path)]
    assert main([*argv, "-r", "__ns:=/r1"]) == 2
    assert "channel '/r1/camera': frequency.min=1.0 exceeds frequency.max=0.5" in (
        capsys.readouterr().err
    )
