"""ROS 2's arguments on dbml's commands, read without rclpy: blocks, params files, ``-p``."""

from __future__ import annotations

from pathlib import Path

import pytest

from dbml.core.errors import TransportError
from dbml.transports.rclpy.rosargs import (
    channel_bounds,
    namespace_of,
    overrides,
    qos_overrides,
    split_ros_args,
)

TABLE1 = """\
/dbm:
  ros__parameters:
    max_bandwidth_in_mbit: 11
    optimization_rate_in_seconds: 1.0
/r1/camera/dbm:
  ros__parameters:
    frequency:
      min: 1.0
      max: 16.0
    priority: 0.25
/r2/camera/dbm:
  ros__parameters:
    frequency: {min: 2.0, max: 8.0}
/r1/dbml_bridge:
  ros__parameters:
    anything: [1, 2]
"""


def params_file(tmp_path: Path, text: str) -> str:
    path = tmp_path / "params.yaml"
    path.write_text(text, encoding="utf-8")
    return str(path)


def test_ros_args_are_every_block_up_to_its_end_marker() -> None:
    argv = ["bridge", "--wait", "3", "--ros-args", "-r", "__ns:=/r1", "--", "--duration", "5"]
    assert split_ros_args(argv) == (
        ["bridge", "--wait", "3", "--duration", "5"],
        ("--ros-args", "-r", "__ns:=/r1"),
    )
    own, ros = split_ros_args(["x", "--ros-args", "-p", "a:=1", "--ros-args", "-r", "b:=c"])
    assert own == ["x"]
    assert ros == ("--ros-args", "-p", "a:=1", "--ros-args", "-r", "b:=c")
    assert split_ros_args(["x", "--", "y"]) == (["x", "--", "y"], ())  # not inside a block


def test_the_namespace_is_the_last_ns_remap() -> None:
    assert namespace_of(()) == "/"
    assert namespace_of(("--ros-args", "-r", "__ns:=/r1")) == "/r1"
    assert namespace_of(("--ros-args", "--remap", "__ns:=r2/", "-r", "__node:=b")) == "/r2"
    assert namespace_of(("--ros-args", "-r", "__ns:=/a", "-r", "__ns:=/b")) == "/b"


def test_a_params_file_gives_dbmls_nodes_values_checked_as_floats(tmp_path: Path) -> None:
    values = overrides(("--ros-args", "--params-file", params_file(tmp_path, TABLE1)))
    assert values == {
        "/dbm/max_bandwidth_in_mbit": 11.0,
        "/dbm/optimization_rate_in_seconds": 1.0,
        "/r1/camera/dbm/frequency/min": 1.0,
        "/r1/camera/dbm/frequency/max": 16.0,
        "/r1/camera/dbm/priority": 0.25,
        "/r2/camera/dbm/frequency/min": 2.0,
        "/r2/camera/dbm/frequency/max": 8.0,
    }  # the bridge's own node is not dbml's: left to rclpy
    assert isinstance(values["/dbm/max_bandwidth_in_mbit"], float)
    assert channel_bounds(values, namespace="/r1") == {"/r1/camera": (1.0, 16.0, 0.25)}
    assert channel_bounds(values) == {
        "/r1/camera": (1.0, 16.0, 0.25),
        "/r2/camera": (2.0, 8.0, None),
    }
    assert channel_bounds(values, namespace="/r3") == {}


def test_later_arguments_win_and_p_sets_a_global(tmp_path: Path) -> None:
    path = params_file(tmp_path, TABLE1)
    values = overrides(("--ros-args", "--params-file", path, "-p", "max_bandwidth_in_mbit:=5"))
    assert values["/dbm/max_bandwidth_in_mbit"] == 5.0
    values = overrides(("--ros-args", "-p", "max_bandwidth_in_mbit:=5", "--params-file", path))
    assert values["/dbm/max_bandwidth_in_mbit"] == 11.0
    assert overrides(("--ros-args", "-p", "use_sim_time:=true")) == {}  # not dbml's


def test_a_wildcard_entry_reaches_every_dbml_node_that_holds_the_name(tmp_path: Path) -> None:
    text = TABLE1 + "/**:\n  ros__parameters:\n    preference: keep_rate\n    strategy: paper\n"
    values = overrides(("--ros-args", "--params-file", params_file(tmp_path, text)))
    assert values["/r1/camera/dbm/preference"] == "keep_rate"
    assert values["/r2/camera/dbm/preference"] == "keep_rate"
    assert values["/dbm/strategy"] == "paper"
    assert "/dbm/preference" not in values


@pytest.mark.parametrize(
    ("text", "error"),
    [
        (
            "/dbm:\n  ros__parameters:\n    max_bandwidth_in_mbit: -3\n",
            r"params\.yaml: /dbm/max_bandwidth_in_mbit=-3 must be",
        ),
        (
            "/dbm:\n  ros__parameters:\n    max_bandwith_in_mbit: 3\n",
            r"params\.yaml: /dbm has no parameter 'max_bandwith_in_mbit'",
        ),
        (
            "/dbm:\n  ros__parameters:\n    status: optimal\n",
            r"/dbm/status='optimal' is written by dbml's optimizer",
        ),
        (
            "/r1/camera/dbm:\n  ros__parameters:\n    frequency: {current_value: 3.0}\n",
            r"/r1/camera/dbm/frequency/current_value=3.0 is written by dbml's optimizer",
        ),
        (
            "/r1/camera/dbm:\n  ros__parameters:\n    priority: [1]\n",
            r"/r1/camera/dbm/priority: parameter value=\[1\] must be",
        ),
        ("/dbm: 3\n", r"node '/dbm' has no ros__parameters"),
        ("- 1\n", r"not a mapping of nodes"),
        ("/dbm: {\n", r"params\.yaml"),
    ],
)
def test_a_bad_params_file_is_refused_naming_the_file_the_field_and_the_value(
    tmp_path: Path, text: str, error: str
) -> None:
    with pytest.raises(TransportError, match=error):
        overrides(("--ros-args", "--params-file", params_file(tmp_path, text)))


def test_a_missing_params_file_is_named(tmp_path: Path) -> None:
    missing = str(tmp_path / "nope.yaml")
    with pytest.raises(TransportError, match=r"^--params-file='.*nope\.yaml': "):
        overrides(("--ros-args", "--params-file", missing))


QOS = """\
/**:
  ros__parameters:
    qos_overrides:
      /r1/camera/optimized:
        publisher: {depth: 5}
/r1/dbml_bridge:
  ros__parameters:
    qos_overrides:
      /r1/camera/optimized:
        publisher:
          reliability: best_effort
          depth: 1
/r2/dbml_bridge:
  ros__parameters:
    qos_overrides:
      /r2/camera/optimized:
        publisher: {reliability: best_effort}
"""


def test_qos_overrides_are_the_commands_nodes_and_the_wildcards(tmp_path: Path) -> None:
    path = params_file(tmp_path, QOS)
    bridge = ("--ros-args", "--params-file", path, "-r", "__ns:=/r1", "-r", "__node:=dbml_bridge")
    assert qos_overrides(bridge) == {
        "qos_overrides./r1/camera/optimized.publisher.depth": 1,  # the node's, after /**
        "qos_overrides./r1/camera/optimized.publisher.reliability": "best_effort",
    }
    assert qos_overrides(("--ros-args", "--params-file", path)) == {  # /dbml: the wildcard's
        "qos_overrides./r1/camera/optimized.publisher.depth": 5,
    }
    p = ("-p", "qos_overrides./r1/camera/optimized.publisher.history:=keep_all")
    assert qos_overrides(("--ros-args", *p))[
        "qos_overrides./r1/camera/optimized.publisher.history"
    ] == ("keep_all")


@pytest.mark.parametrize(
    ("setting", "error"),
    [
        ("publisher: {reliability: sometimes}", r"reliability='sometimes' must be one of"),
        ("publisher: {depth: -1}", r"depth=-1 must be an integer >= 0"),
        ("publisher: {deadline: 3}", r"no such QoS policy"),
        ("subscription: {depth: 3}", r"dbml's QoS overrides are its publishers'"),
    ],
)
def test_a_bad_qos_override_is_refused_naming_it(tmp_path: Path, setting: str, error: str) -> None:
    text = (
        f"/dbml:\n  ros__parameters:\n    qos_overrides:\n      /a/optimized:\n        {setting}\n"
    )
    with pytest.raises(TransportError, match=error):
        qos_overrides(("--ros-args", "--params-file", params_file(tmp_path, text)))
