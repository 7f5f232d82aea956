"""What an experiment measured: per step and robot, over time, and after each link change.

Pure: it takes the frames the operator received and the parameters it saw (``Arrival`` and
``Tick``), and computes per window the allocated and delivered rate, one-way latency
percentiles, losses (sequence gaps) and goodput; per step (after ``settle_s``), as a rolling
time series, and the recovery after each change of the link's rate. One module per concern:
``records`` (what goes in and comes out), ``thresholds`` (what judges a run, named once),
``windows`` (one robot over one window), ``steps`` (``analyse``), ``link`` (link changes and
phases) and ``outage`` (the restoration after an outage).
"""

from dbml.experiment.analysis.outage import outages, recoveries
from dbml.experiment.analysis.records import (
    Analysis,
    Arrival,
    LinkChange,
    LinkPhase,
    Outage,
    Recovery,
    SeriesPoint,
    StepResult,
    StreamLatency,
    Tick,
    Window,
)
from dbml.experiment.analysis.steps import analyse
from dbml.experiment.analysis.thresholds import (
    APPLIED_LAG_S,
    BUDGET_BACK_FRACTION,
    BUDGET_BACK_S,
    FIRST_CUT_S,
    GOODPUT_AFTER_FRACTION,
    GOODPUT_AFTER_S,
    GOODPUT_FRACTION,
    LIVE_FRAMES,
    LIVE_WINDOW_S,
    MAX_P95_MS,
    OUTAGE_AFTER_S,
    OUTAGE_RECOVERY_S,
    PEAK_P95_AFTER_DROP_MS,
    RATE_TOLERANCE,
    RATE_TOLERANCE_HZ,
    RECOVERED_FLOOR_HZ,
    RECOVERED_P95_MS,
    RECOVERY_S,
    STUCK_WINDOW_S,
    WINDOW_S,
    WINDOW_STEP_S,
)
from dbml.experiment.analysis.windows import latest, link_at, rate_hz, settle_s, stream_latency

__all__ = [
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
