"""The Foxglove Studio layout that shows what dbml decided and what it cost.

One layout serves both ways of looking: live (Studio connected to dbml's WebSocket server) and
afterwards (Studio opening the MCAP recording), since both carry the same topics. It is plain data
in the format Studio (1.48, the `@foxglove/studio-base` bundle) loads as a layout: `configById`
(one config per panel id), `layout` (a react-mosaic tree of those ids), `globalVariables`,
`userNodes` and `playbackConfig`. A panel id is `<panel type>!<name>`; Studio reads the type from
the part before the `!`.

The panel types and config keys are the bundle's own: `ImageViewPanel` (`cameraTopic`), `Plot`
(`paths` of `{value, enabled, timestampMethod, label, color}`), `Table` (`topicPath`),
`RawMessages` (`topicPath`, its diff settings, `expansion`) and `Parameters`; every panel's title
is the key `foxglovePanelTitle`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from dbml.transports.base import Variant
from dbml.view.frames import (
    ALLOCATION_TOPIC,
    BUDGET_TOPIC,
    delivered_topic,
    frequency_topic,
    image_topic,
)

__all__ = [
    "DEFAULT_CAMERAS",
    "studio_layout",
]

DEFAULT_CAMERAS = ("/r1/camera", "/r2/camera")
"""The teleop demo's two cameras, each shown as its managed copy `<camera>/optimized`."""

_TITLE = "foxglovePanelTitle"
# One colour per channel, the allocated rate in its strong tone and the delivered rate in its light
# one, so each channel's pair reads as one.
_COLOURS = (
    ("#4e98e2", "#a7cbf0"),
    ("#f5774d", "#fabba6"),
    ("#5cd6a9", "#aeead4"),
    ("#e5a700", "#f2d380"),
    ("#b08ae0", "#d7c4ef"),
)

_IMAGE = "ImageViewPanel"
_PLOT = "Plot!rates"
_TABLE = "Table!allocation"
_BUDGET = "RawMessages!budget"
_PARAMETERS = "Parameters!dbm"


def _image_config(camera: str, *, compressed: bool) -> dict[str, Any]:
    return {
        _TITLE: camera,
        "cameraTopic": Variant.COMPRESSED.key(camera) if compressed else image_topic(camera),
        "enabledMarkerTopics": [],
        "mode": "fit",
        "pan": {"x": 0, "y": 0},
        "rotation": 0,
        "synchronize": False,
        "transformMarkers": False,
        "zoom": 1,
    }


def _plot_path(value: str, label: str, colour: str) -> dict[str, Any]:
    return {
        "value": value,
        "enabled": True,
        "timestampMethod": "receiveTime",
        "label": label,
        "color": colour,
    }


def _plot_config(channels: Sequence[str], *, delivered: bool) -> dict[str, Any]:
    paths = []
    for index, topic in enumerate(channels):
        allocated_colour, delivered_colour = _COLOURS[index % len(_COLOURS)]
        paths.append(_plot_path(f"{frequency_topic(topic)}.data", f"{topic} Hz", allocated_colour))
        if delivered:
            paths.append(
                _plot_path(f"{delivered_topic(topic)}.data", f"{topic} delivered", delivered_colour)
            )
    return {
        _TITLE: "Rates: allocated and delivered (Hz)" if delivered else "Allocated rates (Hz)",
        "paths": paths,
        "minYValue": 0,
        "showXAxisLabels": True,
        "showYAxisLabels": True,
        "showLegend": True,
        "legendDisplay": "left",
        "showPlotValuesInLegend": True,
        "isSynced": True,
        "xAxisVal": "timestamp",
        "sidebarDimension": 260,
    }


def _split(nodes: Sequence[str | dict[str, Any]], direction: str) -> str | dict[str, Any]:
    """Lay nodes side by side in equal shares (react-mosaic splits only in two)."""
    if len(nodes) == 1:
        return nodes[0]
    return {
        "direction": direction,
        "first": nodes[0],
        "second": _split(nodes[1:], direction),
        "splitPercentage": 100 / len(nodes),
    }


def studio_layout(
    *,
    cameras: Sequence[str],
    channels: Sequence[str],
    delivered: bool = True,
    compressed: bool = False,
) -> dict[str, Any]:
    """The layout of dbml's view, for Studio to load as it is (JSON-serialisable).

    Left: one image panel per camera (its `/optimized` topic) above a plot of each channel's
    allocated rate and, with `delivered`, its delivered rate. Right: the allocation as a table,
    below it the budget and the bandwidth estimate (`/dbm/budget`, as text: its numbers are what
    a reader checks) beside the Parameters panel, through which a live session changes dbml's
    parameters.

    Args:
        cameras: Camera topics such as `/r1/camera`; none leaves out the image row.
        channels: Managed topics whose rates are plotted (`<topic>/dbm/frequency/...`).
        delivered: Also plot the delivered rate next to the allocated one.
        compressed: The cameras send JPEG (a ladder): the panels show
            `<topic>/optimized/compressed`.
    """
    config_by_id: dict[str, dict[str, Any]] = {}
    images: list[str | dict[str, Any]] = []
    for index, camera in enumerate(cameras):
        panel_id = f"{_IMAGE}!camera{index}"
        config_by_id[panel_id] = _image_config(camera, compressed=compressed)
        images.append(panel_id)
    config_by_id[_PLOT] = _plot_config(channels, delivered=delivered)
    config_by_id[_TABLE] = {_TITLE: "Allocation", "topicPath": f"{ALLOCATION_TOPIC}.channels"}
    config_by_id[_BUDGET] = {
        _TITLE: "Budget and estimate (Mbit/s)",
        "topicPath": BUDGET_TOPIC,
        "diffEnabled": False,
        "diffMethod": "custom",
        "diffTopicPath": "",
        "showFullMessageForDiff": False,
        "expansion": "all",
    }
    config_by_id[_PARAMETERS] = {_TITLE: "Parameters", "title": "Parameters"}

    left: str | dict[str, Any] = _PLOT
    if images:
        left = {
            "direction": "column",
            "first": _split(images, "row"),
            "second": _PLOT,
            "splitPercentage": 45,
        }
    right = {
        "direction": "column",
        "first": _TABLE,
        "second": {
            "direction": "row",
            "first": _BUDGET,
            "second": _PARAMETERS,
            "splitPercentage": 55,
        },
        "splitPercentage": 40,
    }
    return {
        "configById": config_by_id,
        "layout": {"direction": "row", "first": left, "second": right, "splitPercentage": 50},
        "globalVariables": {},
        "userNodes": {},
        "playbackConfig": {"speed": 1.0},
    }
