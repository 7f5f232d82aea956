"""The quality score: SSIM (Wang et al. 2004) on luma, against the frame as captured.

What the operator sees is a frame on the same screen, so a frame sent at a lower resolution is
scaled back up (each pixel repeated) before it is compared. 7x7 windows, K1 0.01, K2 0.03 and
the sample covariance: scikit-image's defaults, so scores compare with its ``structural_similarity``
(within about 0.002 here); scikit-image itself is not a dependency for one formula on scipy.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.ndimage import uniform_filter

from dbml.core.errors import SpecError

__all__ = ["Reference", "luma", "ssim"]

FloatImage = npt.NDArray[np.float64]

_WINDOW = 7
_COV = _WINDOW * _WINDOW / (_WINDOW * _WINDOW - 1)
"""The sample covariance's correction over a window."""
_K1, _K2, _PEAK = 0.01, 0.03, 255.0
_BT601 = {"rgb8": (0.299, 0.587, 0.114), "bgr8": (0.114, 0.587, 0.299)}


def luma(pixels: npt.NDArray[np.uint8], *, encoding: str = "rgb8") -> FloatImage:
    """The image's luma (BT.601) as floats; a mono8 image is its own."""
    if pixels.ndim == 2:  # noqa: PLR2004
        return pixels.astype(np.float64)
    weights = _BT601.get(encoding)
    if weights is None:
        raise SpecError(f"image encoding={encoding!r} has no luma here (rgb8, bgr8, mono8)")
    out: FloatImage = pixels.astype(np.float64) @ np.asarray(weights)
    return out


def _upscale(image: npt.NDArray[np.float32], shape: tuple[int, int]) -> npt.NDArray[np.float32]:
    if image.shape == shape:
        return image
    fy, fx = -(-shape[0] // image.shape[0]), -(-shape[1] // image.shape[1])
    return np.repeat(np.repeat(image, fy, axis=0), fx, axis=1)[: shape[0], : shape[1]]


class Reference:
    """A reference image's own SSIM terms, computed once for many tests against it."""

    __slots__ = ("_image", "_mean", "_var")

    def __init__(self, image: FloatImage) -> None:
        self._image = np.asarray(image, dtype=np.float32)
        self._mean = uniform_filter(self._image, _WINDOW)
        self._var = _COV * (uniform_filter(self._image * self._image, _WINDOW) - self._mean**2)

    def ssim(self, test: npt.NDArray[np.floating[Any]]) -> float:
        """Mean SSIM of ``test`` against the reference (``test`` scaled up to its size)."""
        x = self._image
        y = _upscale(np.asarray(test, dtype=np.float32), x.shape)
        mx, vx = self._mean, self._var
        my = uniform_filter(y, _WINDOW)
        vy = _COV * (uniform_filter(y * y, _WINDOW) - my * my)
        vxy = _COV * (uniform_filter(x * y, _WINDOW) - mx * my)
        c1, c2 = (_K1 * _PEAK) ** 2, (_K2 * _PEAK) ** 2
        s = ((2 * mx * my + c1) * (2 * vxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
        pad = (_WINDOW - 1) // 2  # the border, as scikit-image crops it
        return float(s[pad:-pad, pad:-pad].mean(dtype=np.float64))


def ssim(reference: FloatImage, test: FloatImage) -> float:
    """Mean SSIM of ``test`` against ``reference`` (luma; ``test`` scaled up to its size)."""
    return Reference(reference).ssim(test)
