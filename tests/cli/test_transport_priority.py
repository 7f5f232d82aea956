"""``--transport-priority``: parsed by name, a bad one a one-line usage error (exit 2)."""

from __future__ import annotations

import pytest

from dbml.cli import main
from dbml.cli.parser import build_parser
from dbml.transports.base import TransportPriority

PUBLISH = ["publish", "/r1/estop", "--size-bytes", "64", "--min-hz", "10", "--max-hz", "10"]


@pytest.mark.parametrize("name", [p.value for p in TransportPriority])
def test_every_class_parses(name: str) -> None:
    args = build_parser().parse_args([*PUBLISH, "--transport-priority", name])
    assert args.transport_priority is TransportPriority(name)


def test_without_the_option_the_priority_maps() -> None:
    assert build_parser().parse_args(PUBLISH).transport_priority is None


def test_a_bad_class_is_one_line_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main([*PUBLISH, "--transport-priority", "urgent"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "transport_priority='urgent' is not one of: real_time, interactive_high" in err
    assert err.count("\n") == 1


def test_testbed_takes_the_urgent_stream_flag() -> None:
    args = build_parser().parse_args(["testbed", "teleop", "--urgent-stream"])
    assert args.urgent_stream
