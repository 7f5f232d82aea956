"""A managed camera on an in-memory fleet: its ladder, the rung pushed, the JPEG that arrives."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator

import numpy as np
import pytest

pytest.importorskip("simplejpeg")

from dbml.core import DbmSettings, LinkSpec, Strategy
from dbml.core.ladder import Preference
from dbml.media.images import Frame, decode_compressed, encode_image
from dbml.media.jpeg import decode_jpeg
from dbml.media.photos import PanCamera
from dbml.protocol import names
from dbml.protocol.ladders import (
    decode_rungs,
    encoding_label,
    parse_encoding,
    parse_rung_label,
)
from dbml.runtime.camera import FALL_S, ManagedCamera
from dbml.testing import Fleet
from dbml.transports.base import Variant


@pytest.fixture
def fleet() -> Iterator[Fleet]:
    fleet = Fleet()
    yield fleet
    fleet.close()


def _camera(
    fleet: Fleet, topic: str, *, priority: float | None = None, preference: Preference | None = None
) -> ManagedCamera:
    return fleet.camera(topic, priority=priority, preference=preference)


def test_a_camera_publishes_its_ladder_and_sends_the_rung_the_optimizer_pushed(
    fleet: Fleet,
) -> None:
    eye = PanCamera(640, 480)
    camera = _camera(fleet, "/r1/camera", priority=1.0, preference=Preference.KEEP_RATE)
    fleet.watch("/r1/camera", remote=Variant.COMPRESSED)
    fleet.budget(3.0)  # 375 kB/s: 16 Hz fits only below about 23 kB a frame
    assert not camera.publish_frame(Frame(eye.frame(), "rgb8"))  # nothing before an allocation
    rungs = decode_rungs(fleet.get(names.ladder("/r1/camera")))
    assert len(rungs) == 21
    assert all(r.jpeg_quality is not None for r in rungs)
    full = {r.jpeg_quality: r.size_bytes for r in rungs if r.scale == 1.0}
    assert full[10] < full[50] < full[95]  # a real JPEG: more quality, more bytes

    result = fleet.optimize()
    pushed = fleet.get(names.encoding("/r1/camera"))
    assert isinstance(pushed, str)
    rate = result.rates_hz["/r1/camera"]
    assert rate == pytest.approx(16.0)  # keep_rate: every frame, detail given up
    chosen = next(r for r in rungs if (r.scale, r.jpeg_quality) == parse_encoding(pushed))
    # The label carries the bytes a frame may carry: the rung's, and the budget's room left.
    (scale, quality), counted = parse_rung_label(pushed)
    assert pushed.startswith(encoding_label(scale, quality) + " ")
    assert (scale, quality) == result.encodings["/r1/camera"]
    assert counted is not None
    assert chosen.size_bytes <= counted + 0.5
    assert rate * counted <= 3e6 / 8 + rate  # rounded to the byte
    assert rate * chosen.size_bytes <= 3e6 / 8 * (1 + 1e-9)
    assert camera.publisher.encoding == (chosen.scale, chosen.jpeg_quality)
    assert fleet.get(names.encoding_applied("/r1/camera")) == pushed

    fleet.advance(1.0)
    assert camera.publish_frame(Frame(eye.frame(), "rgb8"))
    sample = fleet.received["/r1/camera"][-1]
    message = decode_compressed(sample.payload)
    assert message.format == "rgb8; jpeg compressed bgr8"
    pixels = decode_jpeg(message.data)
    assert pixels.shape == (round(480 * chosen.scale), round(640 * chosen.scale), 3)
    assert len(message.data) < 1.5 * chosen.size_bytes


def test_keep_detail_gives_up_frames_where_keep_rate_gives_up_detail(fleet: Fleet) -> None:
    eye = PanCamera(640, 480)
    # No priority: eq. 4's floor is the minimum, so the rate is the allocation's to choose.
    camera = _camera(fleet, "/r1/camera", preference=Preference.KEEP_DETAIL)
    fleet.watch("/r1/camera", remote=Variant.COMPRESSED)
    fleet.budget(3.0)
    camera.publish_frame(Frame(eye.frame(), "rgb8"))
    detail = fleet.optimize()
    fleet.set(names.preference("/r1/camera"), Preference.KEEP_RATE.value)
    rate = fleet.optimize()
    assert detail.rates_hz["/r1/camera"] < rate.rates_hz["/r1/camera"]
    assert detail.quality is not None
    assert rate.quality is not None
    assert detail.quality.quality[0] > rate.quality.quality[0]


def test_a_message_that_is_not_an_image_is_dropped_not_raised(fleet: Fleet) -> None:
    camera = _camera(fleet, "/r1/camera")
    assert camera.publish(b"\x00\x01\x00\x00 not an image") is False
    uint16 = Frame(np.zeros((4, 4), np.uint8), "mono8")
    image = bytearray(encode_image(uint16))
    image[image.find(b"mono8") : image.find(b"mono8") + 5] = b"mono9"
    assert camera.publish(bytes(image)) is False
    assert fleet.get(names.ladder("/r1/camera")) is None


def test_a_bad_ladder_from_the_network_is_reported_and_the_last_good_one_stands(
    fleet: Fleet,
) -> None:
    eye = PanCamera(640, 480)
    camera = _camera(fleet, "/r1/camera")
    fleet.watch("/r1/camera", remote=Variant.COMPRESSED)
    fleet.budget(11.0)
    camera.publish_frame(Frame(eye.frame(), "rgb8"))
    good = fleet.optimize()
    bad = json.dumps([[0, 0.9, 1.0, 50]])
    fleet.network.forge({names.ladder("/r1/camera"): bad})  # a peer that skips the checks
    result = fleet.optimize()
    assert "ladder" in result.message
    assert "size_bytes=0" in result.message
    assert result.encodings == good.encodings
    assert result.rates_hz == good.rates_hz


def test_the_ladder_follows_the_scene_as_the_probe_measures_it_again(fleet: Fleet) -> None:
    camera = fleet.camera("/r1/camera", probe_interval_s=0.05)
    busy = PanCamera(640, 480, offset_px=1400).frame()  # the astronaut and the cat: detail
    camera.publish_frame(Frame(busy, "rgb8"))

    def q95() -> float:
        rungs = decode_rungs(fleet.get(names.ladder("/r1/camera")))
        return next(r.size_bytes for r in rungs if (r.scale, r.jpeg_quality) == (1.0, 95))

    detailed = q95()
    flat = Frame(np.full((480, 640, 3), 128, np.uint8), "rgb8")  # a grey wall: no detail
    deadline = time.monotonic() + 10.0
    while q95() >= detailed / 4:  # a flat frame is a fraction of the detailed one's bytes
        assert time.monotonic() < deadline, "the probe never wrote the new scene's ladder"
        camera.publish_frame(flat)  # offered to the probe, which runs on its own thread
        fleet.advance(0.02)  # a fall is written FALL_S after the probe
        time.sleep(0.02)


def test_a_probe_lowers_the_ladder_only_once_the_frames_sent_since_show_it(fleet: Fleet) -> None:
    """A probe measures one frame: a fall is written ``FALL_S`` after it, a rise at once.

    Written on the probe's word alone, the ladder of a scene panning into detail fell for one
    round and rose again with the next frames, and the allocation flipped the camera's rung and
    rate and back.
    """
    camera = fleet.camera("/r1/camera", priority=1.0, probe_interval_s=1e6)  # probed by hand
    fleet.budget(50.0)
    busy = Frame(PanCamera(640, 480, offset_px=1200, step_px=0).frame(), "rgb8")
    plain = Frame(PanCamera(640, 480, offset_px=0, step_px=0).frame(), "rgb8")
    period_s = 1 / 16

    def q80() -> float:
        assert camera.ladder is not None
        return next(r.size_bytes for r in camera.ladder if (r.scale, r.jpeg_quality) == (1, 80))

    def send(frame: Frame) -> None:
        fleet.advance(period_s)
        assert camera.publish_frame(frame)

    camera.publish_frame(busy)  # measured at once
    fleet.optimize()
    send(busy)
    written = q80()
    send(plain)  # the newest frame offered: the probe's
    camera._probe_once()  # the probe, now (its thread waits 1e6 s)
    assert q80() == written  # a plain frame measured: the busy ladder stands
    for _ in range(round(FALL_S / period_s) - 1):
        send(plain)
    assert q80() == written  # the frames since have not had FALL_S to show it
    send(plain)
    assert q80() < 0.6 * written  # they have: the plain scene's ladder
    camera.publish_frame(busy)  # offered to the probe
    camera._probe_once()
    assert q80() == pytest.approx(written)  # a rise is written at once


def test_frames_of_a_busier_scene_than_the_ladder_says_keep_to_the_budget(fleet: Fleet) -> None:
    """The ladder measured on a plain stretch, then frames twice its bytes, one round a second.

    The ladder's correction and the next round lag the scene; meanwhile each frame is held to
    the bytes the allocation counted it at, so no 1-s window spends more than the budget and a
    frame. (Without the byte window the worst window here is about 530 kB.)
    """
    budget_bytes = 3e6 / 8
    camera = fleet.camera(
        "/r1/camera", priority=1.0, preference=Preference.KEEP_RATE, probe_interval_s=1e6
    )
    fleet.watch("/r1/camera", remote=Variant.COMPRESSED)
    fleet.budget(3.0)
    plain = PanCamera(640, 480, offset_px=0, step_px=0)  # the panorama's plainest stretch
    camera.publish_frame(Frame(plain.frame(), "rgb8"))
    busy = PanCamera(640, 480, offset_px=1200, step_px=8)  # about twice the JPEG bytes
    sent: list[tuple[float, int]] = []
    start = fleet.clock()
    for i in range(16 * 8):
        if i % 16 == 0:
            fleet.optimize()
        fleet.advance(1 / 16)
        if camera.publish_frame(Frame(busy.frame(), "rgb8")):
            data = decode_compressed(fleet.received["/r1/camera"][-1].payload).data
            sent.append((fleet.clock() - start, len(data)))
    worst = max(sum(n for u, n in sent if t <= u < t + 1.0) for t, _ in sent)
    assert worst <= budget_bytes + max(n for _, n in sent)
    assert camera.refused_frames > 0  # the window did the holding: the scene outran the ladder
    late = [t for t, _ in sent if t >= 6.0]  # the ladder caught up: the rate's frames go again
    assert len(late) >= 0.9 * 16 * 2


def test_an_uplink_under_lp_caps_a_laddered_camera_with_its_rung_chosen() -> None:
    """``--uplink``'s links under strategy ``lp``: the rung and the rate within the link's cap."""
    links = (LinkSpec("r1-uplink", 2.0, ("/r1/camera",)),)
    with Fleet(settings=DbmSettings(11.0, 1.0, 1.0, Strategy.LP), links=links) as fleet:
        eye = PanCamera(640, 480)
        cameras = {
            topic: fleet.camera(topic, priority=priority, preference=Preference.KEEP_RATE)
            for topic, priority in (("/r1/camera", 1.0), ("/r2/camera", None))
        }
        for topic, camera in cameras.items():
            fleet.watch(topic, remote=Variant.COMPRESSED)
            camera.publish_frame(Frame(eye.frame(), "rgb8"))
        result = fleet.optimize()
    assert result.quality is not None, result.message  # the quality allocation ran, with links
    spend = dict(zip(result.quality.topics, result.quality.bytes_per_s, strict=True))
    assert spend["/r1/camera"] <= 2.0 * 125_000 * (1 + 1e-9)
    assert result.rates_hz["/r1/camera"] == pytest.approx(16.0)  # keep_rate: detail went first
    assert set(result.encodings) == {"/r1/camera", "/r2/camera"}
    assert sum(spend.values()) <= 11.0 * 125_000 * (1 + 1e-9)
