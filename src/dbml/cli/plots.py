"""The demo's and the testbed's plot: rates, latency and bandwidth over the run (matplotlib)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from dbml.core.extras import require
from dbml.experiment.analysis import MAX_P95_MS, WINDOW_S, SeriesPoint
from dbml.scenarios.teleop import ROBOTS, STEPS

__all__ = ["plot_series"]


def plot_series(
    series: Sequence[SeriesPoint],
    path: Path,
    *,
    step_s: float,
    title: str,
    budget_label: str = "budget",
    capacity: Sequence[tuple[float, float]] = (),
) -> None:
    """Write a PNG of the run to ``path`` (nothing without data).

    Every robot's allocated and delivered rate, its p95 latency (when the frames carry send
    times), and the goodput against the link and the budget. ``capacity``: a recorded trace's
    every change, drawn in place of the link as the windows sampled it.
    """
    if not series:
        return
    require("matplotlib", extra="plot", what="a plot")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with_latency = any(r.latency_p95_ms is not None for p in series for r in p.robots)
    rows = 3 if with_latency else 2
    figure, axes = plt.subplots(rows, 1, figsize=(10, 3 * rows + 1), sharex=True)
    rates, bandwidth = axes[0], axes[-1]
    times = [p.t_s for p in series]
    window = f"{WINDOW_S:g} s"
    for i, camera in enumerate(ROBOTS):
        allocated = [p.robots[i].allocated_hz for p in series]
        if any(a is not None for a in allocated):
            rates.step(times, allocated, where="post", label=f"{camera.robot} allocated")
        delivered = [p.robots[i].delivered_hz for p in series]
        rates.plot(times, delivered, ".", alpha=0.6, label=f"{camera.robot} delivered ({window})")
        if with_latency:
            p95 = [p.robots[i].latency_p95_ms for p in series]
            axes[1].plot(times, p95, label=f"{camera.robot} p95 ({window})")
    rates.set_ylabel("rate (Hz)")
    rates.legend(loc="upper right", fontsize=8)
    if with_latency:
        axes[1].set_ylabel("one-way latency (ms)")
        axes[1].set_yscale("log")
        axes[1].axhline(MAX_P95_MS, color="grey", linestyle=":", linewidth=1)
        axes[1].legend(loc="upper right", fontsize=8)
    bandwidth.plot(times, [p.goodput_mbit for p in series], label=f"goodput ({window})")
    if capacity:
        end = times[-1]
        at = [t for t, _ in capacity if t <= end]
        link = [mbit for t, mbit in capacity if t <= end]
        bandwidth.step(
            [*at, end], [*link, link[-1]], where="post", color="red", lw=0.8, label="link (trace)"
        )
    else:
        bandwidth.step(
            times, [p.link_mbit for p in series], where="post", color="red", label="link"
        )
    budgets = [p.budget_mbit for p in series]
    if any(b is not None for b in budgets):
        bandwidth.step(times, budgets, where="post", color="green", label=budget_label)
    for k in range(len(STEPS) + 1):
        for axis in axes:
            axis.axvline(k * step_s, color="grey", linewidth=0.4)
    bandwidth.set_ylim(bottom=0)
    bandwidth.set_xlabel("time since step 1 (s)")
    bandwidth.set_ylabel("Mbit/s")
    bandwidth.legend(loc="lower right", fontsize=8)
    figure.suptitle(title)
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)
