"""``--foxglove [HOST:]PORT`` and ``--record FILE``: checked before a run, errors naming them."""

from __future__ import annotations

from pathlib import Path

import pytest

from dbml.core.errors import DbmlError
from dbml.view.target import ViewEndpoint, ViewTarget, parse_endpoint


@pytest.mark.parametrize(
    ("text", "endpoint"),
    [
        ("8765", ViewEndpoint("127.0.0.1", 8765)),
        ("0", ViewEndpoint("127.0.0.1", 0)),
        ("0.0.0.0:9000", ViewEndpoint("0.0.0.0", 9000)),
        ("robot-base.local:8765", ViewEndpoint("robot-base.local", 8765)),
        ("[::1]:8765", ViewEndpoint("::1", 8765)),
    ],
)
def test_an_endpoint_is_a_port_with_an_optional_host(text: str, endpoint: ViewEndpoint) -> None:
    assert parse_endpoint(text) == endpoint
    assert parse_endpoint(str(endpoint)) == endpoint


@pytest.mark.parametrize("text", ["", "host:", ":8765", "8765x", "a b:1", "65536", "-1"])
def test_a_bad_endpoint_is_refused_naming_the_flag(text: str) -> None:
    with pytest.raises(DbmlError, match=rf"^--foxglove={text!r}"):
        parse_endpoint(text)


def test_a_recording_is_made_absolute_and_its_directory_must_exist(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    target = ViewTarget.from_flags(None, "demo.mcap")
    assert target == ViewTarget(None, tmp_path / "demo.mcap")
    assert target.record_flag == str(tmp_path / "demo.mcap")
    assert target.foxglove_flag is None
    with pytest.raises(DbmlError, match=r"--record='nowhere/demo.mcap': directory .* not found"):
        ViewTarget.from_flags(None, "nowhere/demo.mcap")
    with pytest.raises(DbmlError, match=r"--record='\.' is a directory"):
        ViewTarget.from_flags(None, ".")


def test_no_flags_no_view() -> None:
    assert ViewTarget.from_flags(None, None) is None
    both = ViewTarget.from_flags("8765", None)
    assert both is not None
    assert both.foxglove_flag == "127.0.0.1:8765"
