"""JPEG at a rung: a resolution scale and a JPEG quality, through libjpeg-turbo (simplejpeg).

simplejpeg was chosen by measurement (../shared/QUALITY.md, re-measured by ``bench/quality.py``):
Pillow, OpenCV and simplejpeg all wrap libjpeg-turbo and give byte-identical files at the same
settings (4:2:0 chroma), but simplejpeg installs in about 1 MB against Pillow's 22 and OpenCV's
153, and encodes from and decodes to numpy arrays without a copy through an image object.
Scaling down is an area average of 2x2 blocks per halving (the camera's own pixels, no
interpolation library): 0.5 and 0.25 are the ladder's resolutions.
"""

from __future__ import annotations

import math
from types import ModuleType

import numpy as np
import numpy.typing as npt

from dbml.core.errors import SpecError
from dbml.core.extras import require
from dbml.core.ladder import MAX_JPEG_QUALITY

__all__ = [
    "PIXEL_CHANNELS",
    "compressed_format",
    "decode_jpeg",
    "encode_jpeg",
    "scale_down",
]

Pixels = npt.NDArray[np.uint8]

PIXEL_CHANNELS = {"rgb8": 3, "bgr8": 3, "mono8": 1}
"""The ``sensor_msgs/msg/Image`` encodings a camera channel may carry, and their channels."""
_COLORSPACE = {"rgb8": "RGB", "bgr8": "BGR", "mono8": "GRAY"}


def _simplejpeg() -> ModuleType:
    return require("simplejpeg", extra="quality", what="JPEG encoding of camera frames")


def compressed_format(encoding: str) -> str:
    """The ``format`` compressed_image_transport writes: ``rgb8; jpeg compressed bgr8``.

    Viewers (rqt_image_view, Foxglove) read the part after ``compressed`` as the decoded
    layout: JPEG holds YCbCr, which OpenCV decodes as BGR (grey stays mono8).
    """
    _channels(encoding)
    return f"{encoding}; jpeg compressed {'mono8' if encoding == 'mono8' else 'bgr8'}"


def _channels(encoding: str) -> int:
    channels = PIXEL_CHANNELS.get(encoding)
    if channels is None:
        raise SpecError(
            f"image encoding={encoding!r} cannot be laddered: one of {', '.join(PIXEL_CHANNELS)}"
        )
    return channels


def scale_down(pixels: Pixels, scale: float) -> Pixels:
    """``pixels`` at ``scale`` of their resolution: 2x2 area averages per halving.

    A scale that is not a power of two takes the nearest halving at or above it, then every
    n-th pixel: the ladder measures what it sends, so the bytes are right whatever the filter.
    """
    if not 0 < scale <= 1:
        raise SpecError(f"scale={scale!r} must be within (0, 1]")
    out = pixels
    halvings = math.floor(math.log2(1 / scale) + 1e-9)
    for _ in range(halvings):
        height, width = out.shape[0] // 2 * 2, out.shape[1] // 2 * 2
        if height == 0 or width == 0:
            break
        block = out[:height, :width].astype(np.uint16)
        summed = block[0::2, 0::2] + block[1::2, 0::2] + block[0::2, 1::2] + block[1::2, 1::2]
        out = ((summed + 2) >> 2).astype(np.uint8)
    rest = scale * 2**halvings
    if rest < 1 - 1e-9:
        step = 1 / rest
        rows = np.arange(0, out.shape[0], step).astype(np.intp)
        cols = np.arange(0, out.shape[1], step).astype(np.intp)
        out = out[rows][:, cols]
    return np.ascontiguousarray(out)


def encode_jpeg(pixels: Pixels, *, encoding: str, quality: int, scale: float = 1.0) -> bytes:
    """``pixels`` (``encoding``'s layout) as a JPEG at ``scale`` and ``quality`` (4:2:0)."""
    channels = _channels(encoding)
    if (
        not isinstance(quality, int)
        or isinstance(quality, bool)
        or not 1 <= quality <= MAX_JPEG_QUALITY
    ):
        raise SpecError(
            f"jpeg quality={quality!r} must be an integer within [1, {MAX_JPEG_QUALITY}]"
        )
    image = pixels if scale == 1 else scale_down(pixels, scale)
    if image.ndim == 2:  # noqa: PLR2004  (height x width: one channel)
        image = image[:, :, None]
    if image.shape[2] != channels:
        raise SpecError(f"an {encoding} image has {channels} channels, not {image.shape[2]}")
    data: bytes = _simplejpeg().encode_jpeg(
        np.ascontiguousarray(image),
        quality=quality,
        colorspace=_COLORSPACE[encoding],
        colorsubsampling="420" if channels == 3 else "Gray",  # noqa: PLR2004
        fastdct=False,
    )
    return data


def decode_jpeg(data: bytes, *, encoding: str = "rgb8") -> Pixels:
    """A JPEG's pixels in ``encoding``'s layout (mono8: height x width); errors name the data.

    A JPEG that does not decode is the sender's fault: ``SpecError``, never a crash.
    """
    channels = _channels(encoding)
    try:
        image = _simplejpeg().decode_jpeg(
            bytes(data), colorspace=_COLORSPACE[encoding], fastdct=False, fastupsample=False
        )
    except ValueError as err:
        raise SpecError(f"a JPEG of {len(data)} bytes does not decode: {err}") from None
    pixels: Pixels = image[:, :, 0] if channels == 1 and image.ndim == 3 else image  # noqa: PLR2004
    return pixels
