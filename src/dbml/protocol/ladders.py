"""A ladder and a chosen encoding as parameters carry them: short texts, checked where they enter.

A publisher measures its camera's ladder and writes it to ``[topic]/dbm/ladder`` as compact
JSON, one ``[size_bytes, quality, scale, jpeg_quality]`` a rung (``jpeg_quality`` null for a
frame sent as it is). The optimizer pushes the rung it chose to
``[topic]/dbm/encoding/current_value`` as a label, ``x0.5 q80`` (half resolution, JPEG quality
80) or ``x1 raw``: the encoder's setting itself, not an index, so a ladder measured again
between the two cannot make a publisher encode what was not meant. The label may end with the
bytes a frame of the rung was counted at, ``x0.5 q80 31234B``: the ladder the allocation used,
which a camera holds its frames to (the ladder may have been written again since). Both arrive
from the network: every error names the value.
"""

from __future__ import annotations

import functools
import json
import math
import re

from dbml.core.errors import SpecError
from dbml.core.ladder import MAX_JPEG_QUALITY, MAX_RUNGS, Rung
from dbml.core.spec import MAX_SIZE_BYTES, short_repr

__all__ = [
    "MAX_LADDER_CHARS",
    "Encoding",
    "decode_rungs",
    "encode_rungs",
    "encoding_label",
    "parse_encoding",
    "parse_rung_label",
]

MAX_LADDER_CHARS = 64 * MAX_RUNGS
"""A ladder's text is at most this long: ``MAX_RUNGS`` rungs of a few numbers each."""

Encoding = tuple[float, int | None]
"""An encoder's setting: the resolution's scale and the JPEG quality (None: sent as it is)."""

_LABEL = re.compile(
    r"^x(?P<scale>[0-9.]+(?:e-?[0-9]+)?) (?:q(?P<q>[0-9]{1,3})|raw)(?: (?P<bytes>[0-9]{1,10})B)?$"
)
_RUNG_FIELDS = 4


def encoding_label(
    scale: float, jpeg_quality: int | None, *, size_bytes: float | None = None
) -> str:
    """``x0.5 q80`` (``x1 raw`` for a frame sent as it is), ``x0.5 q80 31234B`` with a size."""
    label = f"x{scale:g} {'raw' if jpeg_quality is None else f'q{jpeg_quality}'}"
    return label if size_bytes is None else f"{label} {max(round(size_bytes), 1)}B"


def parse_encoding(label: object) -> Encoding:
    """``(scale, jpeg_quality)`` of a label; ``SpecError`` naming it if it is not one."""
    return parse_rung_label(label)[0]


def parse_rung_label(label: object) -> tuple[Encoding, int | None]:
    """The encoding of a label and the bytes it was counted at (None: not said)."""
    found = _LABEL.match(label) if isinstance(label, str) else None
    if found is None:
        raise SpecError(
            f"encoding={short_repr(label)} must look like 'x0.5 q80', 'x1 raw' or 'x1 q80 31234B'"
        )
    try:
        scale = float(found["scale"])
    except ValueError:
        scale = math.nan
    quality = None if found["q"] is None else int(found["q"])
    if not 0 < scale <= 1 or (quality is not None and not 1 <= quality <= MAX_JPEG_QUALITY):
        raise SpecError(
            f"encoding={short_repr(label)}: the scale must be within (0, 1] and the quality within "
            f"[1, {MAX_JPEG_QUALITY}]"
        )
    size = None if found["bytes"] is None else int(found["bytes"])
    if size is not None and not 1 <= size <= MAX_SIZE_BYTES:
        raise SpecError(
            f"encoding={short_repr(label)}: the bytes must be within [1, {MAX_SIZE_BYTES:.0f}]"
        )
    return (scale, quality), size


def encode_rungs(rungs: tuple[Rung, ...]) -> str:
    """The ladder's parameter text (rounded: bytes to the byte, quality to 1e-4)."""
    return json.dumps(
        [[round(r.size_bytes), round(r.quality, 4), r.scale, r.jpeg_quality] for r in rungs],
        separators=(",", ":"),
    )


def decode_rungs(text: object) -> tuple[Rung, ...]:
    """The rungs of a ladder's text; ``SpecError`` naming the value if it is not a ladder.

    Cached by text: the optimizer reads every channel's ladder every round, and a ladder is
    rewritten only when it moved.
    """
    if not isinstance(text, str) or len(text) > MAX_LADDER_CHARS:
        raise SpecError(f"ladder={short_repr(text)} must be a text of at most {MAX_LADDER_CHARS}")
    return _decode(text)


@functools.lru_cache(maxsize=1024)
def _decode(text: str) -> tuple[Rung, ...]:
    try:
        raw = json.loads(text)
    except ValueError:
        raise SpecError(f"ladder={short_repr(text)} is not JSON") from None
    if not isinstance(raw, list) or not raw:
        raise SpecError(f"ladder={short_repr(text)} must be a non-empty list of rungs")
    if len(raw) > MAX_RUNGS:
        raise SpecError(f"ladder holds {len(raw)} rungs, more than {MAX_RUNGS}")
    rungs = []
    for item in raw:
        if not isinstance(item, list) or len(item) != _RUNG_FIELDS:
            raise SpecError(
                f"ladder rung={short_repr(item)} must be [size_bytes, quality, scale, jpeg_quality]"
            )
        size, quality, scale, jpeg = item
        if isinstance(jpeg, float) and jpeg.is_integer():
            jpeg = int(jpeg)
        try:
            rungs.append(Rung(size, quality, scale=scale, jpeg_quality=jpeg))
        except (SpecError, TypeError) as err:
            raise SpecError(f"ladder rung={short_repr(item)}: {err}") from None
    return tuple(rungs)
