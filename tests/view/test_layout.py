from __future__ import annotations

import json
from typing import Any

import pytest

from dbml.view import layout as layout_module
from dbml.view.layout import DEFAULT_CAMERAS, studio_layout

CHANNELS = ("/r1/camera", "/r2/camera", "/r1/lidar")


def _leaves(node: Any) -> list[str]:
    """The panel ids of a react-mosaic tree, left to right."""
    if isinstance(node, str):
        return [node]
    assert set(node) <= {"direction", "first", "second", "splitPercentage"}, node
    assert node["direction"] in {"row", "column"}
    assert 0 < node["splitPercentage"] < 100
    return _leaves(node["first"]) + _leaves(node["second"])


def _of_type(layout: dict[str, Any], kind: str) -> dict[str, dict[str, Any]]:
    return {i: c for i, c in layout["configById"].items() if i.split("!")[0] == kind}


def _plot_paths(layout: dict[str, Any]) -> list[str]:
    (plot,) = _of_type(layout, "Plot").values()
    return [path["value"] for path in plot["paths"]]


def test_all_is_sorted() -> None:
    assert layout_module.__all__ == sorted(layout_module.__all__)


def test_the_default_cameras_are_the_demo_s() -> None:
    from dbml.scenarios.teleop import ROBOTS

    assert tuple(camera.topic for camera in ROBOTS) == DEFAULT_CAMERAS


@pytest.mark.parametrize("delivered", [True, False])
@pytest.mark.parametrize("cameras", [DEFAULT_CAMERAS, ("/r1/camera",), ()])
def test_every_panel_in_the_tree_has_a_config(cameras: tuple[str, ...], *, delivered: bool) -> None:
    layout = studio_layout(cameras=cameras, channels=CHANNELS, delivered=delivered)
    leaves = _leaves(layout["layout"])
    assert len(leaves) == len(set(leaves))
    assert set(leaves) == set(layout["configById"])
    assert all("!" in panel_id for panel_id in leaves)


def test_the_format_studio_loads() -> None:
    layout = studio_layout(cameras=DEFAULT_CAMERAS, channels=CHANNELS)
    assert set(layout) == {"configById", "layout", "globalVariables", "userNodes", "playbackConfig"}
    assert layout["globalVariables"] == {}
    assert layout["userNodes"] == {}
    assert layout["playbackConfig"] == {"speed": 1.0}
    assert json.loads(json.dumps(layout)) == layout


def test_one_image_panel_per_camera_on_its_optimized_topic() -> None:
    layout = studio_layout(cameras=DEFAULT_CAMERAS, channels=CHANNELS)
    images = _of_type(layout, "ImageViewPanel")
    assert sorted(c["cameraTopic"] for c in images.values()) == [
        "/r1/camera/optimized",
        "/r2/camera/optimized",
    ]
    assert studio_layout(cameras=(), channels=CHANNELS)["configById"].keys().isdisjoint(images)


def test_plot_of_allocated_and_delivered_rates() -> None:
    layout = studio_layout(cameras=DEFAULT_CAMERAS, channels=CHANNELS)
    assert _plot_paths(layout) == [
        f"{topic}/dbm/frequency/{field}.data"
        for topic in CHANNELS
        for field in ("current_value", "delivered_value")
    ]
    (plot,) = _of_type(layout, "Plot").values()
    assert all(p["enabled"] and p["timestampMethod"] == "receiveTime" for p in plot["paths"])
    assert len({p["color"] for p in plot["paths"]}) == len(plot["paths"])


def test_plot_without_delivered_rates() -> None:
    layout = studio_layout(cameras=DEFAULT_CAMERAS, channels=CHANNELS, delivered=False)
    assert _plot_paths(layout) == [f"{t}/dbm/frequency/current_value.data" for t in CHANNELS]


def test_allocation_budget_and_parameters_panels() -> None:
    layout = studio_layout(cameras=DEFAULT_CAMERAS, channels=CHANNELS)
    (table,) = _of_type(layout, "Table").values()
    assert table["topicPath"] == "/dbm/allocation.channels"
    (budget,) = _of_type(layout, "RawMessages").values()
    assert budget["topicPath"] == "/dbm/budget"
    assert len(_of_type(layout, "Parameters")) == 1
