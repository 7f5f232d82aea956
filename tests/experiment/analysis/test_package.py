"""``dbml.experiment.analysis`` keeps the names it had as one module, each importable."""

from __future__ import annotations

from dbml.experiment import analysis

PUBLIC = [
    "APPLIED_LAG_S",
    "BUDGET_BACK_FRACTION",
    "BUDGET_BACK_S",
    "FIRST_CUT_S",
    "GOODPUT_AFTER_FRACTION",
    "GOODPUT_AFTER_S",
    "GOODPUT_FRACTION",
    "LIVE_FRAMES",
    "LIVE_WINDOW_S",
    "MAX_P95_MS",
    "OUTAGE_AFTER_S",
    "OUTAGE_RECOVERY_S",
    "PEAK_P95_AFTER_DROP_MS",
    "RATE_TOLERANCE",
    "RATE_TOLERANCE_HZ",
    "RECOVERED_FLOOR_HZ",
    "RECOVERED_P95_MS",
    "RECOVERY_S",
    "STUCK_WINDOW_S",
    "WINDOW_S",
    "WINDOW_STEP_S",
    "Analysis",
    "Arrival",
    "LinkChange",
    "LinkPhase",
    "Outage",
    "Recovery",
    "SeriesPoint",
    "StepResult",
    "StreamLatency",
    "Tick",
    "Window",
    "analyse",
    "latest",
    "link_at",
    "outages",
    "rate_hz",
    "recoveries",
    "settle_s",
    "stream_latency",
]
"""The module's names but ``CUT_STAMP`` (the estimator's decision time is a field now), and
what came after it (the recoveries after an outage)."""


def test_the_package_exports_the_module_s_names() -> None:
    assert analysis.__all__ == PUBLIC
    assert sorted(PUBLIC, key=lambda n: (not n.isupper(), n)) == PUBLIC
    assert all(hasattr(analysis, name) for name in PUBLIC)
