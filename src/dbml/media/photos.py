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
from dbml.media.jpeg import decode_jpeg, scale_down

__all__ = ["PANORAMA_HEIGHT", "PanCamera", "panorama"]

PANORAMA_HEIGHT = 480
DEFAULT_STEP_PX = 4
"""How far the window slides a frame at full resolution (64 px/s at 16 Hz)."""


@functools.cache
def panorama() -> npt.NDArray[np.uint8]:
    """The photographs side by side, RGB, ``PANORAMA_HEIGHT`` high (decoded once)."""
    data = resources.files("dbml.media").joinpath("data/panorama.jpg").read_bytes()
    pixels = decode_jpeg(data, encoding="rgb8")
    pixels.flags.writeable = False
    return pixels


class PanCamera:
    """RGB frames of ``width`` x ``height`` sliding over the panorama, starting at ``offset``.

    A smaller camera (320x240) sees the panorama at its own scale, so both robots of the
    paper's scenario look at the same photographs.
    """

    def __init__(
        self,
        width: int = 640,
        height: int = 480,
        *,
        offset: int = 0,
        step_px: int = DEFAULT_STEP_PX,
    ) -> None:
        scale = height / PANORAMA_HEIGHT
        if scale not in (1.0, 0.5, 0.25):
            raise SpecError(f"camera height={height!r}: one of 480, 240, 120")
        self._strip = panorama() if scale == 1 else scale_down(panorama(), scale)
        if not 0 < width <= self._strip.shape[1]:
            raise SpecError(f"camera width={width!r} must be within (0, {self._strip.shape[1]}]")
        self.width, self.height = width, height
        self._travel = self._strip.shape[1] - width
        self._step = max(1, round(step_px * scale))
        self._position = offset * self._step
        self.frames = 0

    def frame(self) -> npt.NDArray[np.uint8]:
        """The next frame (a fresh array: a driver's buffer is its own)."""
        period = 2 * self._travel
        at = self._position % period if period else 0
        x = at if at <= self._travel else period - at
        self._position += self._step
        self.frames += 1
        return np.array(self._strip[:, x : x + self.width])
