"""A camera's ladder, measured on its own frames: each rung's bytes and SSIM.

``measure_ladder`` encodes one frame at every rung of a grid (resolution scales x JPEG
qualities), decodes each and scores it against the frame (``dbml.media.ssim``). A publisher
does this in the background a few times a minute (``dbml.runtime.camera``), so the ladder the
optimizer allocates on follows the scene. The quality is scored on a quarter of the frame's
pixels (every second row and column of the luma, both sides alike): a probe of 21 rungs costs
about a fifth of what the full-size score would, and the score moves by a few thousandths.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from dbml.core.ladder import MAX_RUNGS, Rung
from dbml.media.jpeg import decode_jpeg, encode_jpeg, scale_down
from dbml.media.ssim import Reference, luma

__all__ = ["DEFAULT_QUALITIES", "DEFAULT_SCALES", "measure_ladder", "reference", "score"]

DEFAULT_SCALES = (1.0, 0.5, 0.25)
DEFAULT_QUALITIES = (10, 30, 50, 70, 80, 90, 95)
"""The grid probed: 21 rungs (``MAX_RUNGS`` bounds it), ``../shared/QUALITY.md``'s table."""


def measure_ladder(
    pixels: npt.NDArray[np.uint8],
    *,
    encoding: str,
    scales: Sequence[float] = DEFAULT_SCALES,
    qualities: Sequence[int] = DEFAULT_QUALITIES,
) -> tuple[Rung, ...]:
    """Every rung of the grid measured on ``pixels``: bytes of the JPEG, SSIM of its decoding."""
    grid = [(s, q) for s in scales for q in qualities]
    if not 0 < len(grid) <= MAX_RUNGS:
        raise ValueError(f"a ladder of {len(grid)} rungs: 1 to {MAX_RUNGS}")
    sent = reference(pixels, encoding=encoding)
    shape = (int(pixels.shape[0]), int(pixels.shape[1]))
    rungs = []
    for scale in scales:
        scaled = scale_down(pixels, scale)  # once per resolution, for all its qualities
        for quality in qualities:
            data = encode_jpeg(scaled, encoding=encoding, quality=quality)
            rungs.append(Rung(float(len(data)), score(sent, data, shape=shape), scale, quality))
    return tuple(rungs)


def reference(pixels: npt.NDArray[np.uint8], *, encoding: str) -> Reference:
    """A frame as ``score`` compares with it: its luma on every second row and column."""
    return Reference(luma(pixels[::2, ::2], encoding=encoding))


def score(sent: Reference, data: bytes, *, shape: tuple[int, int]) -> float:
    """SSIM in [0, 1] of a JPEG against the frame it encodes (``shape``: that frame's).

    Decoded as grey (libjpeg-turbo hands back the JPEG's own luma, no colour to convert),
    scaled back to the frame's size, then sampled as the reference is. ``SpecError`` if the
    JPEG does not decode.
    """
    decoded = decode_jpeg(data, encoding="mono8").astype(np.float32)
    factor = max(1, round(shape[0] / max(decoded.shape[0], 1)))
    full = _repeat(decoded, factor)[: shape[0], : shape[1]]
    return min(max(sent.ssim(full[::2, ::2]), 0.0), 1.0)


def _repeat(image: npt.NDArray[np.float32], factor: int) -> npt.NDArray[np.float32]:
    if factor <= 1:
        return image
    return np.repeat(np.repeat(image, factor, axis=0), factor, axis=1)
