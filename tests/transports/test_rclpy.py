"""The rclpy transport against real rclpy: names, framing, parameters as ROS 2 sees them, graph.

Each test claims its own ROS 2 domain; the ROS 2 side of a check (``ros2 param set``, a foreign
node) is a plain rclpy node in a context of its own, as another process's would be.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from dbml.core.errors import TransportError
from dbml.protocol.keys import encode_batch
from dbml.protocol.metadata import MessageMeta
from dbml.protocol.schema import PARAMETERS, Kind, Scope, Writer
from dbml.runtime.priority import PRIORITY_INTERVAL_S, PriorityTopic
from dbml.transports.base import Role, Sample, Variant
from dbml.transports.rclpy.params import UNATTRIBUTED_S, descriptor
from tests.conftest import wait_for

rclpy = pytest.importorskip("rclpy")  # before dbml's rclpy module: the ROS 1 environment lacks it

from rclpy.parameter import Parameter as RosParameter  # noqa: E402
from rclpy.qos import ReliabilityPolicy  # noqa: E402
from std_msgs.msg import Float64, String  # noqa: E402

from dbml.harness.ros2node import private_node  # noqa: E402
from dbml.transports.rclpy.graph import host_of_node, node_name_for  # noqa: E402
from dbml.transports.rclpy.transport import (  # noqa: E402
    ALLOCATION_QOS,
    BYTES_TYPE,
    RclpyTransport,
    frame_bytes,
    message_class,
    sample_meta,
    unframe_bytes,
)
from tests.rclpy_tools import param_describe, param_set  # noqa: E402


@given(st.from_regex(r"[A-Za-z0-9_\-.~]{1,40}", fullmatch=True))
def test_a_node_name_says_its_host(host: str) -> None:
    name = node_name_for(host)
    assert host_of_node(name) == host
    assert name.replace("_", "").isalnum()


def test_a_foreign_node_name_says_no_host() -> None:
    assert host_of_node("camera_driver") is None
    assert host_of_node("dbml_r1") is None


@given(st.binary(max_size=2_000))
def test_bytes_travel_framed_as_uint8_multi_array(payload: bytes) -> None:
    assert unframe_bytes(frame_bytes(payload)) == payload


def test_the_framing_is_rclpys_own_uint8_multi_array() -> None:
    from rclpy.serialization import deserialize_message, serialize_message
    from std_msgs.msg import UInt8MultiArray

    assert BYTES_TYPE == "std_msgs/msg/UInt8MultiArray"
    parsed = deserialize_message(frame_bytes(b"abc"), UInt8MultiArray)
    assert bytes(parsed.data) == b"abc"
    assert unframe_bytes(serialize_message(UInt8MultiArray(data=list(b"xyz")))) == b"xyz"


def test_a_missing_type_names_what_to_install() -> None:
    with pytest.raises(TransportError, match=r"pip install ros-nav2-msgs"):
        message_class("nav2_msgs/msg/Costmap")
    with pytest.raises(TransportError, match=r"type='Image' must look like"):
        message_class("Image")


@pytest.mark.integration
def test_ros2_param_set_on_the_optimizers_node(ros_domain: int) -> None:
    optimizer = RclpyTransport(host="ground", domain_id=ros_domain)
    observer = RclpyTransport(host="observer", domain_id=ros_domain)
    try:
        optimizer.params.set("/dbm/status", "optimal")  # the optimizer's write: it hosts /dbm
        optimizer.params.set("/dbm/max_bandwidth_in_mbit", 11.0)
        with private_node("operator", domain_id=ros_domain) as operator:
            result = param_set(operator, "/dbm", "max_bandwidth_in_mbit", 5)  # an integer
            assert result.successful, result.reason
            wait_for(lambda: observer.params.get("/dbm/max_bandwidth_in_mbit") == 5.0, what="5")
            assert optimizer.params.get("/dbm/max_bandwidth_in_mbit") == 5.0

            refused = param_set(operator, "/dbm", "max_bandwidth_in_mbit", -3)
            assert not refused.successful
            assert "out of range" in refused.reason  # rclpy's, by the descriptor's range

            owned = param_set(operator, "/dbm", "status", "infeasible")
            assert not owned.successful
            assert "optimizer" in owned.reason
        assert optimizer.params.get("/dbm/max_bandwidth_in_mbit") == 5.0
        assert optimizer.params.get("/dbm/status") == "optimal"
        assert observer.params.get("/dbm/status") == "optimal"
    finally:
        observer.close()
        optimizer.close()


@pytest.mark.integration
def test_every_parameter_is_described_as_the_schema_says(ros_domain: int) -> None:
    """``ros2 param describe``: each parameter's range, description and writers; rclpy's range."""
    optimizer = RclpyTransport(host="ground", domain_id=ros_domain)
    robot = RclpyTransport(host="r1", domain_id=ros_domain)
    try:
        optimizer.params.set("/dbm/status", "optimal")  # it hosts /dbm
        robot.params.set("/r1/camera/dbm/frequency/max", 16.0)  # it hosts /r1/camera/dbm
        with private_node("operator", domain_id=ros_domain) as operator:
            for node, scope in (("/dbm", Scope.GLOBAL), ("/r1/camera/dbm", Scope.CHANNEL)):
                parameters = [p for p in PARAMETERS if p.scope is scope]
                described = param_describe(operator, node, [p.ros2_name for p in parameters])
                assert [d.name for d in described] == [p.ros2_name for p in parameters]
                for parameter, found in zip(parameters, described, strict=True):
                    assert found.description == parameter.doc
                    assert found.dynamic_typing
                    writers = [w.value for w in Writer if w in parameter.writers]
                    assert f"written by: {', '.join(writers)}" in found.additional_constraints
                    if parameter.kind is Kind.NUMBER:
                        (bounds,) = found.floating_point_range
                        (integers,) = found.integer_range
                        if parameter.minimum is not None:  # the least integer in the range
                            assert bounds.from_value == parameter.minimum
                            least, low = integers.from_value, parameter.minimum
                            if parameter.exclusive_minimum:
                                assert low < least <= low + 1
                            else:
                                assert low <= least < low + 1
                        if parameter.maximum is not None:  # the greatest
                            assert bounds.to_value == parameter.maximum
                            assert parameter.maximum - 1 < integers.to_value <= parameter.maximum
                    else:
                        assert not found.floating_point_range
                        assert not found.integer_range
            refused = param_set(operator, "/r1/camera/dbm", "priority", 1.5)
            assert not refused.successful
            assert "out of range" in refused.reason  # rclpy's own check of the float range
            refused = param_set(operator, "/r1/camera/dbm", "priority", 2)  # an integer
            assert not refused.successful
            assert "out of range" in refused.reason
            refused = param_set(operator, "/dbm", "max_bandwidth_in_mbit", 0.0)
            assert not refused.successful  # in the float range; the schema's minimum is exclusive
            assert "max_bandwidth_in_mbit=0" in refused.reason
            taken = param_set(operator, "/r1/camera/dbm", "priority", 1)  # an integer, in range
            assert taken.successful, taken.reason
            wait_for(lambda: robot.params.get("/r1/camera/dbm/priority") == 1.0, what="1.0")
    finally:
        robot.close()
        optimizer.close()


@pytest.mark.integration
def test_the_optimized_copys_qos_follows_the_params_files_overrides(
    ros_domain: int, tmp_path: Path
) -> None:
    """``qos_overrides.<topic>.publisher.*`` for the command's node, as any ROS 2 publisher's."""
    params = tmp_path / "qos.yaml"
    params.write_text(
        "/r1/dbml_bridge:\n  ros__parameters:\n    qos_overrides:\n"
        "      /r1/camera/optimized:\n        publisher: {reliability: best_effort, depth: 1}\n"
    )
    ros_args = ("--ros-args", "-r", "__ns:=/r1", "-r", "__node:=dbml_bridge")
    robot = RclpyTransport(
        host="r1", domain_id=ros_domain, ros_args=(*ros_args, "--params-file", str(params))
    )
    try:
        robot.declare_publisher("/r1/camera", Variant.OPTIMIZED)
        robot.declare_publisher("/r1/scan", Variant.OPTIMIZED)  # no override: dbml's own QoS
        with private_node("observer", domain_id=ros_domain) as observer:

            def reliability(topic: str) -> Any:
                found = observer.get_publishers_info_by_topic(topic)
                return found[0].qos_profile.reliability if found else None

            wait_for(lambda: reliability("/r1/camera/optimized") is not None, what="camera")
            wait_for(lambda: reliability("/r1/scan/optimized") is not None, what="scan")
            assert reliability("/r1/camera/optimized") == ReliabilityPolicy.BEST_EFFORT
            assert reliability("/r1/scan/optimized") == ReliabilityPolicy.RELIABLE
        assert (
            robot.node.get_parameter("qos_overrides./r1/camera/optimized.publisher.depth").value
            == 1
        )
    finally:
        robot.close()


@pytest.mark.integration
def test_a_channels_parameters_live_on_its_publishers_node(ros_domain: int) -> None:
    robot = RclpyTransport(host="r1", domain_id=ros_domain)
    ground = RclpyTransport(host="ground", domain_id=ros_domain)
    try:
        robot.params.set("/r1/camera/dbm/frequency/max", 16.0)  # the publisher's own
        wait_for(lambda: ground.params.get("/r1/camera/dbm/frequency/max") == 16.0, what="max")
        ground.params.set("/r1/camera/dbm/priority", 0.8)  # an operator's, through the service
        wait_for(lambda: robot.params.get("/r1/camera/dbm/priority") == 0.8, what="priority")
        wait_for(lambda: ground.confirm_param("/r1/camera/dbm/priority", timeout_s=0), what="ack")
        with private_node("operator", domain_id=ros_domain) as operator:
            refused = param_set(operator, "/r1/camera/dbm", "frequency.max", 100.0)
            assert not refused.successful
            assert "publisher" in refused.reason
            assert robot.params.get("/r1/camera/dbm/frequency/max") == 16.0
    finally:
        ground.close()
        robot.close()


@pytest.mark.integration
def test_a_float64_priority_sets_the_channels_priority_and_a_flood_keeps_the_rule(
    ros_domain: int, caplog: pytest.LogCaptureFixture
) -> None:
    """``ros2 topic pub`` (or a mission node) of ``std_msgs/msg/Float64`` on its topic."""
    name = "/r1/camera/dbm/priority"
    robot = RclpyTransport(host="r1", domain_id=ros_domain)
    heard = PriorityTopic(robot, "/r1/camera")  # what the channel's managed publisher runs
    writes: list[tuple[float, object]] = []
    robot.params.watch(lambda n, v: writes.append((time.monotonic(), v)) if n == name else None)
    try:
        with private_node("mission", domain_id=ros_domain) as mission:
            publisher = mission.create_publisher(Float64, name, 10)
            wait_for(lambda: publisher.get_subscription_count() > 0, what="the subscription")

            def applied(value: float) -> Callable[[], bool]:
                def check() -> bool:  # a reliable publisher's first messages may precede matching
                    publisher.publish(Float64(data=value))
                    return robot.params.get(name) == value

                return check

            publisher.publish(Float64(data=7.0))  # out of range: refused, named
            wait_for(lambda: "ignoring a priority" in caplog.text, what="the refusal")
            assert f"{name}=7.0" in caplog.text
            assert robot.params.get(name) is None
            wait_for(applied(0.3), what="0.3")
            started = time.monotonic()
            flood = [round(0.001 * i, 3) for i in range(1, 1_000)]
            for value in flood:
                publisher.publish(Float64(data=value))
            wait_for(lambda: robot.params.get(name) == flood[-1], what="the flood's newest")
        during = [t for t, _v in writes if t >= started]
        span_s = during[-1] - during[0]
        assert len(during) <= span_s / PRIORITY_INTERVAL_S + 1, (len(during), span_s)
        assert len(during) < len(flood) / 10
    finally:
        heard.close()
        robot.close()


@pytest.mark.integration
def test_only_the_dbm_node_allocates(ros_domain: int, caplog: pytest.LogCaptureFixture) -> None:
    robot = RclpyTransport(host="r1", domain_id=ros_domain)
    optimizer = RclpyTransport(host="ground", domain_id=ros_domain)
    try:
        robot.params.set("/r1/camera/dbm/frequency/max", 16.0)
        optimizer.params.set("/dbm/status", "optimal")
        wait_for(lambda: optimizer.params.get("/r1/camera/dbm/frequency/max") == 16.0, what="max")
        with private_node("forger", domain_id=ros_domain) as forger:
            fake = forger.create_publisher(String, "/dbm/allocation", ALLOCATION_QOS)
            wait_for(lambda: fake.get_subscription_count() >= 2, what="the forger's matches")
            batch = encode_batch({"/r1/camera/dbm/frequency/current_value": 16.0}, 1, "x")
            fake.publish(String(data=batch.decode()))
            optimizer.params.set("/r1/camera/dbm/frequency/current_value", 4.0)
            wait_for(
                lambda: robot.params.get("/r1/camera/dbm/frequency/current_value") == 4.0,
                what="the optimizer's allocation",
            )
            # Alone, with nothing of the optimizer's after it: held, then dropped, named.
            forged = {
                "/r1/camera/dbm/frequency/current_value": 16.0,
                "/r1/camera/dbm/managed": True,
            }
            fake.publish(String(data=encode_batch(forged, 2, "x").decode()))
            wait_for(
                lambda: "not the /dbm node" in caplog.text,
                timeout_s=UNATTRIBUTED_S + 5,
                what="the forgery's refusal",
            )
            assert robot.params.get("/r1/camera/dbm/frequency/current_value") == 4.0
            assert robot.params.get("/r1/camera/dbm/managed") is not True
    finally:
        optimizer.close()
        robot.close()


@pytest.mark.integration
def test_the_graph_is_the_dds_endpoints_by_host(ros_domain: int) -> None:
    robot = RclpyTransport(host="r1", domain_id=ros_domain)
    ground = RclpyTransport(host="ground", domain_id=ros_domain)
    try:
        publisher = robot.declare_publisher("/r1/camera", Variant.OPTIMIZED)
        handle = ground.subscribe("/r1/camera", lambda _s: None, Variant.OPTIMIZED)
        wanted = {
            (Role.PUBLISHER, "r1", "/r1/camera", Variant.OPTIMIZED),
            (Role.SUBSCRIBER, "ground", "/r1/camera", Variant.OPTIMIZED),
        }

        def seen() -> set[tuple[Role, str, str, Variant]]:
            return {(e.role, e.host, e.topic, e.variant) for e in robot.graph.entries()}

        wait_for(lambda: wanted <= seen(), what="both endpoints with their hosts")
        handle.close()
        wait_for(
            lambda: (Role.SUBSCRIBER, "ground", "/r1/camera", Variant.OPTIMIZED) not in seen(),
            what="the subscription's departure",
        )
        publisher.close()
    finally:
        ground.close()
        robot.close()


@pytest.mark.integration
def test_a_foreign_subscription_of_the_optimized_copy_is_remote(ros_domain: int) -> None:
    robot = RclpyTransport(host="r1", domain_id=ros_domain)
    try:
        robot.set_topic_type("/r1/camera", "sensor_msgs/msg/Image")
        robot.declare_publisher("/r1/camera", Variant.OPTIMIZED)
        from sensor_msgs.msg import Image

        with private_node("rviz", domain_id=ros_domain) as rviz:
            rviz.create_subscription(Image, "/r1/camera/optimized", lambda _m: None, 10)

            def foreign() -> set[str]:
                return {
                    e.host
                    for e in robot.graph.entries()
                    if e.role is Role.SUBSCRIBER and e.variant is Variant.OPTIMIZED
                }

            wait_for(lambda: bool(foreign()) and "r1" not in foreign(), what="a remote consumer")
        wait_for(lambda: not foreign(), what="its departure")
    finally:
        robot.close()


@pytest.mark.integration
def test_a_sample_carries_ddss_sequence_and_send_time(ros_domain: int) -> None:
    """What ``--estimate`` needs travels in DDS's sample info: seq and source timestamp."""
    robot = RclpyTransport(host="r1", domain_id=ros_domain)
    ground = RclpyTransport(host="ground", domain_id=ros_domain)
    try:
        got: list[Sample] = []
        ground.subscribe("/r1/camera", got.append, Variant.OPTIMIZED)
        publisher = robot.declare_publisher("/r1/camera", Variant.OPTIMIZED)
        wait_for(lambda: publisher.has_subscribers, what="the match")
        before_ns = time.time_ns()
        for _ in range(3):
            publisher.put(b"frame")
        wait_for(lambda: len(got) == 3, what="three samples")
        metas = [MessageMeta.decode(sample.attachment) for sample in got]
        assert [meta.seq for meta in metas] == [1, 2, 3]
        assert all(before_ns <= meta.sent_ns <= time.time_ns() for meta in metas)
        assert all(math.isnan(meta.rate_hz) for meta in metas)
    finally:
        ground.close()
        robot.close()


def test_sample_info_without_a_sequence_is_no_metadata() -> None:
    assert sample_meta({"source_timestamp": 5, "publication_sequence_number": None}) is None
    assert sample_meta(None) is None


@pytest.mark.integration
def test_an_operators_value_can_precede_the_robot_that_hosts_it(ros_domain: int) -> None:
    """Nobody hosts ``/r1/camera/dbm`` yet: the operator's process does, until the robot starts.

    The robot then hosts its channel for good, with the operator's priority; the operator's
    provisional node goes, and its later writes reach the robot's node.
    """
    operator = RclpyTransport(host="ground", domain_id=ros_domain)
    robot: RclpyTransport | None = None
    try:
        operator.params.set("/r1/camera/dbm/priority", 0.7)
        wait_for(lambda: _hosts(operator, "/r1/camera/dbm"), what="the provisional host")
        robot = RclpyTransport(host="r1", domain_id=ros_domain)
        robot.params.set("/r1/camera/dbm/frequency/max", 16.0)  # the robot's own: it hosts
        # Each step waits for DDS discovery (up to ~3 s: the new node, then its services).
        wait_for(
            lambda: not _hosts(operator, "/r1/camera/dbm"), timeout_s=HANDOVER_S, what="hand-over"
        )
        assert _claimed_by(ros_domain, "/r1/camera") == "r1"  # the endpoint that says so
        wait_for(
            lambda: robot is not None and robot.params.get("/r1/camera/dbm/priority") == 0.7,
            timeout_s=HANDOVER_S,
            what="0.7 on the robot",
        )
        operator.params.set("/r1/camera/dbm/priority", 0.2)
        wait_for(
            lambda: robot is not None and robot.params.get("/r1/camera/dbm/priority") == 0.2,
            what="0.2",
        )
        wait_for(lambda: operator.confirm_param("/r1/camera/dbm/priority", timeout_s=0), what="ack")
    finally:
        if robot is not None:
            robot.close()
        operator.close()


HANDOVER_S = 15.0


@pytest.mark.integration
def test_what_the_host_announced_while_this_process_hosted_its_node_is_read_after(
    ros_domain: int,
) -> None:
    """A provisional host ignores the node's announcements (it knows its own values)...

    ...and a read of the node meanwhile is answered by its own node first (both serve
    ``get_parameters``), so when it gives the node up it reads the node from its host again.
    The robot here is a plain node (no dbml) that hosts ``/r1/camera/dbm`` with a channel's
    parameters, changes a value, and only then claims it (a dbml host claims at once, and the
    graph may show the claim after the node, as in a fleet's start).
    """
    operator = RclpyTransport(host="ground", domain_id=ros_domain)
    try:
        operator.params.set("/r1/camera/dbm/priority", 0.7)
        wait_for(lambda: _hosts(operator, "/r1/camera/dbm"), what="the provisional host")
        with private_node("dbm", domain_id=ros_domain, namespace="/r1/camera") as robot:
            for parameter in PARAMETERS:  # as a channel's host declares them
                if parameter.scope is Scope.CHANNEL:
                    robot.declare_parameter(parameter.ros2_name, None, descriptor(parameter))
            robot.set_parameters([RosParameter("frequency.max", value=16.0)])
            wait_for(
                lambda: "/r1/camera/dbm" in operator._sync._live,  # the graph shows the robot's
                timeout_s=HANDOVER_S,
                what="the robot's node",
            )
            robot.set_parameters([RosParameter("frequency.max", value=12.0)])
            claim = robot.create_publisher(String, "/r1/camera/dbm/host", ALLOCATION_QOS)
            claim.publish(String(data="r1"))
            wait_for(
                lambda: not _hosts(operator, "/r1/camera/dbm"),
                timeout_s=HANDOVER_S,
                what="hand-over",
            )
            wait_for(
                lambda: operator.params.get("/r1/camera/dbm/frequency/max") == 12.0,
                timeout_s=HANDOVER_S,
                what="the robot's 12.0 in the operator's view",
            )
    finally:
        operator.close()


def _claimed_by(domain_id: int, channel: str) -> str:
    """The host a foreign node reads on ``[topic]/dbm/host``: who hosts the channel for good."""
    got: list[str] = []
    with private_node("reader", domain_id=domain_id) as reader:
        reader.create_subscription(
            String, f"{channel}/dbm/host", lambda m: got.append(m.data), ALLOCATION_QOS
        )
        wait_for(lambda: bool(got), timeout_s=HANDOVER_S, what="the claim's host")
    return got[0]


def _hosts(transport: RclpyTransport, node: str) -> bool:
    """Whether ``transport`` hosts ``node``, asked on its executor thread."""
    import threading

    answer: list[bool] = []
    done = threading.Event()

    def ask() -> None:
        answer.append(transport._sync.hosts(node))
        done.set()

    transport.call_soon(ask)
    assert done.wait(5.0), "the executor thread answered"
    return answer[0]


@pytest.mark.integration
def test_hostile_requests_and_events_change_nothing(ros_domain: int) -> None:
    """A request rclpy cannot parse, a deletion, a forged event: no thread dies, no value moves.

    A ``SetParameters`` with an unknown value type raised out of rclpy's own service callback
    and killed the executor; a ``/parameter_events`` message naming a node it does not host
    was believed.
    """
    from rcl_interfaces.msg import Parameter as ParameterMsg
    from rcl_interfaces.msg import ParameterEvent, ParameterType

    robot = RclpyTransport(host="r1", domain_id=ros_domain)
    ground = RclpyTransport(host="ground", domain_id=ros_domain)
    try:
        robot.params.set("/r1/camera/dbm/frequency/max", 16.0)
        robot.params.set("/r1/camera/dbm/priority", 0.5)
        wait_for(lambda: ground.params.get("/r1/camera/dbm/priority") == 0.5, what="0.5")
        with private_node("hostile", domain_id=ros_domain) as hostile:
            weird = ParameterMsg(name="priority")
            weird.value.type = 99
            param_set_raw(hostile, "/r1/camera/dbm", weird)  # unanswered or refused
            deleted = ParameterMsg(name="priority")
            deleted.value.type = ParameterType.PARAMETER_NOT_SET
            result = param_set_raw(hostile, "/r1/camera/dbm", deleted)
            assert result is not None
            assert not result.successful
            assert "cannot be deleted" in result.reason
            forged = ParameterEvent(node="/r1/camera/dbm")
            fake = ParameterMsg(name="frequency.max")
            fake.value.type = ParameterType.PARAMETER_DOUBLE
            fake.value.double_value = 1000.0
            forged.changed_parameters = [fake]
            events = hostile.create_publisher(ParameterEvent, "/parameter_events", 10)
            wait_for(lambda: events.get_subscription_count() >= 2, what="the forger's matches")
            for _ in range(3):
                events.publish(forged)
            ground.params.set("/r1/camera/dbm/priority", 0.25)  # after the attacks, in order
            wait_for(lambda: robot.params.get("/r1/camera/dbm/priority") == 0.25, what="0.25")
            wait_for(lambda: ground.params.get("/r1/camera/dbm/priority") == 0.25, what="echo")
        assert robot.alive
        assert ground.alive
        assert ground.params.get("/r1/camera/dbm/frequency/max") == 16.0
    finally:
        ground.close()
        robot.close()


ANSWER_S = 2.0
"""How long a hostile request's answer is waited for (it may never come)."""


def param_set_raw(node: Any, target: str, parameter: Any) -> Any:
    """One ``SetParameters`` call carrying ``parameter`` as given; its result, or None."""
    from rcl_interfaces.srv import SetParameters

    client: Any = node.create_client(SetParameters, f"{target}/set_parameters")
    try:
        assert client.wait_for_service(timeout_sec=5.0), f"{target} never answered"
        future = client.call_async(SetParameters.Request(parameters=[parameter]))
        answered = threading.Event()
        future.add_done_callback(lambda _f: answered.set())
        response: Any = future.result() if answered.wait(ANSWER_S) else None
        return None if response is None else response.results[0]
    finally:
        node.destroy_client(client)


@pytest.mark.integration
def test_a_name_ros_2_refuses_is_refused_by_name(ros_domain: int) -> None:
    transport = RclpyTransport(host="r1", domain_id=ros_domain)
    try:
        with pytest.raises(TransportError, match=r"topic='/r1/cam-front' is not a ROS 2 name"):
            transport.subscribe("/r1/cam-front", lambda _s: None)
        with pytest.raises(TransportError, match=r"topic='/r1/cam.front' is not a ROS 2 name"):
            transport.params.set("/r1/cam.front/dbm/priority", 0.5)
        assert transport.params.get("/r1/cam.front/dbm/priority") is None
    finally:
        transport.close()


@pytest.mark.integration
def test_closing_sends_what_is_queued(ros_domain: int) -> None:
    robot = RclpyTransport(host="r1", domain_id=ros_domain)
    operator = RclpyTransport(host="ground", domain_id=ros_domain)
    try:
        robot.params.set("/r1/camera/dbm/frequency/max", 16.0)
        wait_for(lambda: operator.params.get("/r1/camera/dbm/frequency/max") == 16.0, what="max")
        wait_for(lambda: operator.wait_for_peers(0), what="the operator settled")
        operator.params.set("/r1/camera/dbm/priority", 0.42)
        operator.close()
        wait_for(lambda: robot.params.get("/r1/camera/dbm/priority") == 0.42, what="0.42")
    finally:
        operator.close()
        robot.close()
