"""A camera's ladder: the encodings its frames may take, each with its bytes and its quality.

A rung is one encoding of a channel's frames (a resolution scale and a JPEG quality) with what
it costs (bytes per frame) and what it keeps (a quality score in [0, 1]: SSIM against the full
frame, as the publisher measures it on its own camera). With a ladder, the allocation chooses a
rung as well as a rate (``dbml.core.quality``). ``Preference`` says which to give up first when
the budget is short: an event chooses it, as it chooses the priority.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from dbml.core.errors import SpecError
from dbml.core.spec import MAX_SIZE_BYTES, check_number

__all__ = [
    "MAX_JPEG_QUALITY",
    "MAX_RUNGS",
    "PREFERENCE_TERMS",
    "Ladder",
    "Preference",
    "Rung",
]

MAX_RUNGS = 32
"""The most rungs a ladder holds: 3 resolutions x 6 JPEG qualities, with room to spare. A ladder
arrives from the network; each rung costs the optimizer work every round."""
MAX_JPEG_QUALITY = 100


class Preference(enum.StrEnum):
    """What a channel gives up first when the budget is short (WebRTC's degradation preference).

    ``keep_rate``: detail goes first (a robot near an obstacle: the operator needs every frame);
    ``keep_detail``: frames go first (a victim found: the operator needs to see it clearly);
    ``balanced``: both, by the utility's plain terms.
    """

    BALANCED = "balanced"
    KEEP_RATE = "keep_rate"
    KEEP_DETAIL = "keep_detail"


PREFERENCE_TERMS: Mapping[Preference, tuple[float, float | None]] = {
    Preference.BALANCED: (1.0, 1.0),
    Preference.KEEP_RATE: (1.0, None),
    Preference.KEEP_DETAIL: (8.0, 0.25),
}
"""Per preference, the utility's terms (``dbml.core.quality``): ``gamma``, the quality's
exponent, and the rate's knee ``k`` in Hz (None: the channel's maximum rate)."""


@dataclass(frozen=True, slots=True)
class Rung:
    """One encoding: ``size_bytes`` per frame for a ``quality`` score in [0, 1].

    ``scale`` is the resolution's fraction of the camera's (1.0, 0.5, 0.25); ``jpeg_quality``
    the encoder's setting (1-100), None for a frame sent as it is.
    """

    size_bytes: float
    quality: float
    scale: float = 1.0
    jpeg_quality: int | None = None

    def __post_init__(self) -> None:
        owner = "rung"
        size = check_number(
            self.size_bytes, field="size_bytes", owner=owner, minimum=0, exclusive_minimum=True
        )
        check_number(size, field="size_bytes", owner=owner, maximum=MAX_SIZE_BYTES)
        quality = check_number(self.quality, field="quality", owner=owner, minimum=0, maximum=1)
        scale = check_number(
            self.scale, field="scale", owner=owner, minimum=0, maximum=1, exclusive_minimum=True
        )
        jpeg = self.jpeg_quality
        if jpeg is not None and (
            isinstance(jpeg, bool) or not isinstance(jpeg, int) or not 1 <= jpeg <= MAX_JPEG_QUALITY
        ):
            raise SpecError(
                f"{owner}: jpeg_quality={jpeg!r} must be an integer within [1, {MAX_JPEG_QUALITY}]"
            )
        object.__setattr__(self, "size_bytes", size)
        object.__setattr__(self, "quality", quality)
        object.__setattr__(self, "scale", scale)


@dataclass(frozen=True, slots=True)
class Ladder:
    """A channel's rungs, its quality floor and its preference.

    Rungs below ``min_quality`` are never chosen; a ladder none of whose rungs reaches it keeps
    its best rung (the allocation says so). Order does not matter.
    """

    rungs: tuple[Rung, ...]
    min_quality: float = 0.0
    preference: Preference = Preference.BALANCED
    choices: tuple[int, ...] = field(init=False, repr=False, compare=False)
    """The rungs the allocation may choose (indices): those at or above the quality floor and
    not dominated (another as good for no more bytes); or the best one if none is."""
    choice_sizes: tuple[float, ...] = field(init=False, repr=False, compare=False)
    choice_qualities: tuple[float, ...] = field(init=False, repr=False, compare=False)
    choice_table: npt.NDArray[np.float64] = field(init=False, repr=False, compare=False)
    """The choices as one read-only array, the solver's rows: size, quality, rung
    index, quality ** gamma, the rate's knee (NaN: the maximum rate) and position."""

    def __post_init__(self) -> None:
        rungs = tuple(self.rungs)
        if not rungs:
            raise SpecError("ladder: rungs=[] must hold at least one rung")
        if len(rungs) > MAX_RUNGS:
            raise SpecError(f"ladder: rungs holds {len(rungs)} rungs, more than {MAX_RUNGS}")
        for rung in rungs:
            if not isinstance(rung, Rung):
                raise SpecError(f"ladder: rung={rung!r} is not a Rung")
        floor = check_number(
            self.min_quality, field="min_quality", owner="ladder", minimum=0, maximum=1
        )
        try:
            preference = Preference(self.preference)
        except ValueError:
            names = ", ".join(p.value for p in Preference)
            raise SpecError(
                f"ladder: preference={self.preference!r} is not one of: {names}"
            ) from None
        object.__setattr__(self, "rungs", rungs)
        object.__setattr__(self, "min_quality", floor)
        object.__setattr__(self, "preference", preference)
        choices = _choices(rungs, floor)
        object.__setattr__(self, "choices", choices)
        object.__setattr__(self, "choice_sizes", tuple(rungs[j].size_bytes for j in choices))
        object.__setattr__(self, "choice_qualities", tuple(rungs[j].quality for j in choices))
        gamma, knee = PREFERENCE_TERMS[preference]
        table = np.array(
            [
                self.choice_sizes,
                self.choice_qualities,
                [float(j) for j in choices],
                [q**gamma for q in self.choice_qualities],
                [math.nan if knee is None else knee] * len(choices),
                [float(i) for i in range(len(choices))],
            ],
            dtype=float,
        )
        table.flags.writeable = False
        object.__setattr__(self, "choice_table", table)

    @property
    def meets_floor(self) -> bool:
        """Whether some rung reaches ``min_quality`` (else its best rung is the only choice)."""
        return any(r.quality >= self.min_quality for r in self.rungs)


def _choices(rungs: tuple[Rung, ...], floor: float) -> tuple[int, ...]:
    kept = [j for j, r in enumerate(rungs) if r.quality >= floor]
    if not kept:
        return (max(range(len(rungs)), key=lambda j: (rungs[j].quality, -j)),)
    # Cheapest first (ties: the better, then the earlier); a rung no better than a cheaper one
    # is never worth choosing.
    kept.sort(key=lambda j: (rungs[j].size_bytes, -rungs[j].quality, j))
    choices: list[int] = []
    for j in kept:
        if not choices or rungs[j].quality > rungs[choices[-1]].quality:
            choices.append(j)
    return tuple(choices)
