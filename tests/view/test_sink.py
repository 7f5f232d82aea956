"""The foxglove-sdk sink: a real WebSocket server and MCAP file, and a client as the app is."""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from pathlib import Path

import pytest

from dbml.protocol.schema import ParamError, ParamValue
from dbml.view import frames
from dbml.view.client import FoxgloveClient
from dbml.view.frames import LogLevel
from dbml.view.sink import MAX_REFUSALS_PER_S, Sink
from dbml.view.target import ViewEndpoint

BUDGET = "/dbm/max_bandwidth_in_mbit"


class Settings:
    """One settable number that refuses negatives, as the view's settings refuse bad values."""

    def __init__(self) -> None:
        self.values: dict[str, ParamValue] = {BUDGET: 11.0, "/dbm/strategy": "paper"}

    def current(self) -> Mapping[str, ParamValue]:
        return dict(self.values)

    def set(self, name: str, value: object) -> ParamValue:
        if not isinstance(value, float | int) or value <= 0:
            raise ParamError(f"{name}={value!r} must be > 0")
        self.values[name] = float(value)
        return float(value)


@pytest.fixture
def sink(tmp_path: Path) -> Iterator[tuple[Sink, Settings, Path]]:
    settings = Settings()
    record = tmp_path / "view.mcap"
    made = Sink(endpoint=ViewEndpoint("127.0.0.1", 0), record=record, settings=settings)
    yield made, settings, record
    made.close()


def test_parameters_are_shown_set_and_refused_with_their_reason(
    sink: tuple[Sink, Settings, Path],
) -> None:
    server, settings, _ = sink
    assert server.address is not None
    assert server.address.port > 0
    with FoxgloveClient(f"ws://{server.address}", timeout_s=5) as client:
        client.send({"op": "getParameters", "parameterNames": [], "id": "all"})
        client.set_parameter("bad", BUDGET, -3)
        client.set_parameter("good", BUDGET, 5.5)
        assert client.pump(lambda: client.answer("good") is not None, timeout_s=5)
        shown = client.answer("all")
        assert shown is not None
        assert {p["name"]: p["value"] for p in shown["parameters"]} == {
            BUDGET: 11.0,
            "/dbm/strategy": "paper",
        }
        bad = client.answer("bad")
        assert bad is not None
        assert bad["parameters"][0]["value"] == 11.0
        good = client.answer("good")
        assert good is not None
        assert good["parameters"][0]["value"] == 5.5
        assert client.statuses() == [f"refused: {BUDGET}=-3 must be > 0"]
    assert settings.values[BUDGET] == 5.5


def test_every_channel_is_recorded_with_its_schema(sink: tuple[Sink, Settings, Path]) -> None:
    server, _, record = sink
    server.log_json(
        frames.ALLOCATION_TOPIC, frames.ALLOCATION_SCHEMA, {"round": 1, "channels": []}, time_ns=5
    )
    server.log_json(
        "/r1/camera/dbm/frequency/current_value", frames.FREQUENCY_SCHEMA, {"data": 2.0}, time_ns=6
    )
    server.log_cdr(
        "/r1/camera/optimized", "sensor_msgs/msg/Image", "uint8[] data", b"\x00\x01", time_ns=7
    )
    server.log_text(LogLevel.WARNING, "infeasible: too little", time_ns=8)
    server.refused("refused: /dbm/max_bandwidth_in_mbit=-3")
    server.close()
    server.close()  # idempotent

    from mcap.reader import make_reader

    with record.open("rb") as stream:
        reader = make_reader(stream)
        got = [
            (
                channel.topic,
                schema.name,
                schema.encoding,
                channel.message_encoding,
                message.log_time,
            )
            for schema, channel, message in reader.iter_messages()
            if schema is not None
        ]
    assert got[:4] == [
        ("/dbm/allocation", "dbml.Allocation", "jsonschema", "json", 5),
        ("/r1/camera/dbm/frequency/current_value", "dbml.Frequency", "jsonschema", "json", 6),
        ("/r1/camera/optimized", "sensor_msgs/msg/Image", "ros2msg", "cdr", 7),
        ("/dbm/log", "foxglove.Log", "protobuf", "protobuf", 8),
    ]
    assert [g[0] for g in got[4:]] == ["/dbm/log"]  # the refusal, on the log too


def test_a_flood_of_values_is_refused_whole_and_refusals_are_bounded(
    sink: tuple[Sink, Settings, Path],
) -> None:
    server, settings, _ = sink
    assert server.address is not None
    flood = [{"name": f"/r{i}/camera/dbm/priority", "value": 0.5} for i in range(100)]
    with FoxgloveClient(f"ws://{server.address}", timeout_s=5) as client:
        client.send({"op": "setParameters", "parameters": flood, "id": "flood"})
        for k in range(3 * MAX_REFUSALS_PER_S):
            client.set_parameter(f"bad{k}", BUDGET, -k - 1)
        last = f"bad{3 * MAX_REFUSALS_PER_S - 1}"
        assert client.pump(lambda: client.answer(last) is not None, timeout_s=5)
        statuses = client.statuses()
    assert statuses[0] == "refused: a setParameters of 100 values (at most 32): none set"
    assert len(statuses) <= MAX_REFUSALS_PER_S * 2  # two seconds at most, not 31 statuses
    assert settings.values[BUDGET] == 11.0


def test_an_address_in_use_is_one_line_naming_the_flag(sink: tuple[Sink, Settings, Path]) -> None:
    server, _, _ = sink
    assert server.address is not None
    from dbml.core.errors import DbmlError

    with pytest.raises(DbmlError, match=rf"^--foxglove={server.address}: "):
        Sink(endpoint=server.address, record=None)
