"""Frames for the analysis's tests: a stream at a steady rate, delay and size."""

from __future__ import annotations

from dbml.experiment.analysis import Arrival


def stream(
    robot: int, *, hz: float, start: float, end: float, delay: float, size: int, skip: int = -1
) -> list[Arrival]:
    """Frames of ``robot`` sent at ``hz`` from ``start`` to ``end``, frame ``skip`` lost."""
    frames = []
    seq, t = 0, start
    while t < end:
        if seq != skip:
            frames.append(Arrival(robot, seq, t, t + delay, size, hz))
        seq += 1
        t += 1 / hz
    return frames
