"""JPEG at a rung, images in CDR, SSIM, the measured ladder and the photographs' camera."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("simplejpeg")

from dbml.core.errors import SpecError
from dbml.media.images import (
    Frame,
    decode_compressed,
    decode_image,
    encode_compressed,
    encode_image,
)
from dbml.media.jpeg import compressed_format, decode_jpeg, encode_jpeg, scale_down
from dbml.media.ladder import measure_ladder
from dbml.media.photos import PanCamera, frame_position, position_frame_id
from dbml.media.ssim import ssim


def test_scaling_down_averages_each_block() -> None:
    pixels = np.arange(16, dtype=np.uint8).reshape(4, 4)
    half = scale_down(pixels, 0.5)
    assert half.tolist() == [[3, 5], [11, 13]]  # (0+1+4+5)/4 = 2.5 -> 3 (rounded half up)
    assert scale_down(pixels, 0.25).shape == (1, 1)


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "mono8"])
def test_a_frame_survives_jpeg_at_a_high_quality(encoding: str) -> None:
    frame = PanCamera(640, 480).frame()
    if encoding == "bgr8":
        frame = np.ascontiguousarray(frame[:, :, ::-1])
    if encoding == "mono8":
        frame = np.ascontiguousarray(frame[:, :, 1])
    data = encode_jpeg(frame, encoding=encoding, quality=95)
    back = decode_jpeg(data, encoding=encoding)
    assert back.shape == frame.shape
    assert np.abs(back.astype(int) - frame.astype(int)).mean() < 4
    small = decode_jpeg(
        encode_jpeg(frame, encoding=encoding, quality=95, scale=0.5), encoding=encoding
    )
    assert small.shape[:2] == (240, 320)


def test_the_format_string_is_compressed_image_transports() -> None:
    assert compressed_format("rgb8") == "rgb8; jpeg compressed bgr8"
    assert compressed_format("bgr8") == "bgr8; jpeg compressed bgr8"
    assert compressed_format("mono8") == "mono8; jpeg compressed mono8"
    with pytest.raises(SpecError, match="encoding='16UC1'"):
        compressed_format("16UC1")


def test_bytes_that_are_not_a_jpeg_are_an_error_naming_them() -> None:
    with pytest.raises(SpecError, match="a JPEG of 5 bytes does not decode"):
        decode_jpeg(b"hello")


def test_images_survive_cdr() -> None:
    pixels = PanCamera(320, 240).frame()
    frame = Frame(pixels, "rgb8", stamp_ns=1_700_000_000_123_456_789, frame_id="r1")
    back = decode_image(encode_image(frame))
    assert back.encoding == "rgb8"
    assert back.frame_id == "r1"
    assert back.stamp_ns == frame.stamp_ns
    assert np.array_equal(back.pixels, pixels)
    data = encode_jpeg(pixels, encoding="rgb8", quality=50)
    message = decode_compressed(encode_compressed(frame, data, format="rgb8; jpeg compressed bgr8"))
    assert message.data == data
    assert message.stamp_ns == frame.stamp_ns


def test_bytes_that_are_not_an_image_are_an_error() -> None:
    with pytest.raises(SpecError, match="is not a sensor_msgs/msg/Image"):
        decode_image(b"\x00\x01\x00\x00" + bytes(3))


def test_ssim_of_constants_is_the_luminance_term() -> None:
    # Two flat images: no variance, so SSIM = (2ab + c1) / (a^2 + b^2 + c1) (Wang et al. 2004).
    a, b = 100.0, 120.0
    c1 = (0.01 * 255) ** 2
    got = ssim(np.full((32, 32), a), np.full((32, 32), b))
    assert got == pytest.approx((2 * a * b + c1) / (a * a + b * b + c1), rel=1e-5)


def test_ssim_falls_as_noise_rises() -> None:
    rng = np.random.default_rng(1)
    image = PanCamera(320, 240).frame()[:, :, 1].astype(float)
    assert ssim(image, image) == pytest.approx(1.0)
    scores = [ssim(image, image + rng.normal(0, sigma, image.shape)) for sigma in (2, 8, 32)]
    assert scores[0] > scores[1] > scores[2]


def test_a_measured_ladder_costs_more_bytes_for_more_quality() -> None:
    rungs = measure_ladder(PanCamera(640, 480, offset_px=300).frame(), encoding="rgb8")
    for scale in (1.0, 0.5, 0.25):
        row = sorted((r for r in rungs if r.scale == scale), key=lambda r: r.jpeg_quality or 0)
        sizes = [r.size_bytes for r in row]
        scores = [r.quality for r in row]
        assert sizes == sorted(sizes)
        assert scores[-1] > scores[0]
    best_small = max(r.quality for r in rungs if r.scale == 0.25)
    best_full = max(r.quality for r in rungs if r.scale == 1.0)
    assert best_full > best_small  # a quarter of the resolution loses detail JPEG cannot add


def test_the_camera_moves_over_the_photographs() -> None:
    camera = PanCamera(640, 480)
    first, second = camera.frame(), camera.frame()
    assert first.shape == (480, 640, 3)
    assert not np.array_equal(first, second)
    assert np.array_equal(first[:, 4:], second[:, :-4])  # four pixels to the right
    assert PanCamera(320, 240).frame().shape == (240, 320, 3)
    small = PanCamera(160, 120, speed_px_per_s=40)
    assert small.at(0.0) == 0
    assert small.at(1.0) == 10  # a quarter of the resolution: a quarter of the pixels
    assert np.array_equal(small.window(small.at(1.0)), small.window(10))
    with pytest.raises(SpecError, match="x=-1"):
        small.window(-1)
    assert frame_position(position_frame_id(1234)) == 1234
    assert frame_position("camera") is None
