"""A camera moving over real photographs: the paper's experiment on frames that are real.

``data/panorama.jpg`` joins five photographs side by side at 480 pixels high (see
``data/LICENSE.md``: public domain or CC0, from scikit-image's data). A ``PanCamera`` looks at a
window of it that slides across and back, a few pixels a frame, so each frame differs from the
last as a moving robot's camera does, and the scene's detail (so its JPEG bytes) changes as it
goes: sky, a face, a cat's fur, a star field.
"""

from __future__ import annotations

import functools
from importlib import resources

import numpy as np
import numpy.typing as npt

from dbml.core.errors import SpecError
from dbml.media.jpeg import decode_jpeg, encode_jpeg, scale_down

__all__ = [
    "DEFAULT_SPEED_PX_PER_S",
    "DEFAULT_STEP_PX",
    "PANORAMA_HEIGHT",
    "SCALES",
    "PanCamera",
    "frame_position",
    "panorama",
    "position_frame_id",
    "quality_for_size",
]

PANORAMA_HEIGHT = 480
DEFAULT_STEP_PX = 4
"""How far ``frame()`` slides the window at full resolution."""
DEFAULT_SPEED_PX_PER_S = 60.0
"""How fast ``at`` slides it at full resolution: the panorama there and back in 90 s."""
SCALES = (1.0, 0.5, 0.25)


@functools.cache
def panorama() -> npt.NDArray[np.uint8]:
    """The photographs side by side, RGB, ``PANORAMA_HEIGHT`` high (decoded once)."""
    data = resources.files("dbml.media").joinpath("data/panorama.jpg").read_bytes()
    pixels = decode_jpeg(data, encoding="rgb8")
    pixels.flags.writeable = False
    return pixels


class PanCamera:
    """RGB frames of ``width`` x ``height`` sliding over the panorama, and back.

    ``window(x)`` is the frame at ``x`` pixels from the left (of the panorama at the camera's
    scale): the operator remakes from it the frame that was sent. ``at(t_s)`` is where a camera
    moving ``speed_px_per_s`` is at ``t_s``; ``frame()`` the next of a camera that moves
    ``step_px`` a frame. A smaller camera (320x240, 160x120) sees the panorama at its own
    scale, so every robot of the paper's scenario looks at the same photographs.
    """

    def __init__(
        self,
        width: int = 640,
        height: int = 480,
        *,
        offset_px: int = 0,
        step_px: int = DEFAULT_STEP_PX,
        speed_px_per_s: float = DEFAULT_SPEED_PX_PER_S,
    ) -> None:
        scale = height / PANORAMA_HEIGHT
        if scale not in SCALES:
            raise SpecError(f"camera height={height!r}: one of 480, 240, 120")
        self._strip = panorama() if scale == 1 else scale_down(panorama(), scale)
        if not 0 < width <= self._strip.shape[1]:
            raise SpecError(f"camera width={width!r} must be within (0, {self._strip.shape[1]}]")
        self.width, self.height, self.scale = width, height, scale
        self._travel = int(self._strip.shape[1]) - width
        self._step = max(1, round(step_px * scale))
        self._speed = speed_px_per_s * scale
        self._offset = round(offset_px * scale)
        self._position = self._offset

    @property
    def travel_px(self) -> int:
        """How far the window's left edge goes: ``window`` takes ``0`` to this."""
        return self._travel

    def _fold(self, position: float) -> int:
        """A position along the way there and back, as the window's left edge."""
        period = 2 * self._travel
        if not period:
            return 0
        at = int(position) % period
        return at if at <= self._travel else period - at

    def at(self, t_s: float) -> int:
        """The window's left edge ``t_s`` seconds after the camera started."""
        return self._fold(self._offset + self._speed * t_s)

    def window(self, x: int) -> npt.NDArray[np.uint8]:
        """The frame whose left edge is ``x`` (a fresh array); ``SpecError`` off the panorama."""
        if not 0 <= x <= self._travel:
            raise SpecError(f"pan position x={x!r} is off the panorama [0, {self._travel}]")
        return np.array(self._strip[:, x : x + self.width])

    def frame(self) -> npt.NDArray[np.uint8]:
        """The next frame of a camera that moves ``step_px`` a frame."""
        x = self._fold(self._position)
        self._position += self._step
        return self.window(x)


_FRAME_ID_PREFIX = "pan/"


def position_frame_id(x: int) -> str:
    """The ``frame_id`` a panning camera stamps its frame with: where its window was."""
    return f"{_FRAME_ID_PREFIX}{x}"


def frame_position(frame_id: str) -> int | None:
    """The window's position a ``frame_id`` says (None: not a panning camera's)."""
    if not frame_id.startswith(_FRAME_ID_PREFIX):
        return None
    digits = frame_id[len(_FRAME_ID_PREFIX) :]
    return int(digits) if digits.isdigit() and len(digits) <= 6 else None  # noqa: PLR2004


_SAMPLED_WINDOWS = 16


@functools.cache
def quality_for_size(size_bytes: int, width: int = 640, height: int = 480) -> int:
    """The JPEG quality whose frames of this panning camera average nearest ``size_bytes``.

    The rate-only baseline of the paper's experiment: the one quality whose frames are the
    paper's size (84,000 B at 640x480 is quality 91 here), measured on ``_SAMPLED_WINDOWS``
    windows across the panorama (about 0.2 s, once per process).
    """
    camera = PanCamera(width, height)
    positions = np.linspace(0, camera.at(0) + camera.travel_px, _SAMPLED_WINDOWS).astype(int)
    frames = [camera.window(int(x)) for x in positions]

    def mean_bytes(quality: int) -> float:
        return float(
            np.mean([len(encode_jpeg(f, encoding="rgb8", quality=quality)) for f in frames])
        )

    low, high = 1, 100  # the bytes grow with the quality: bisect for the two around the size
    while high - low > 1:
        mid = (low + high) // 2
        if mean_bytes(mid) <= size_bytes:
            low = mid
        else:
            high = mid
    return min((low, high), key=lambda q: abs(mean_bytes(q) - size_bytes))
