"""One periodic worker thread, for every node part that acts on a period (and on a poke).

The optimizer (every period and at once on a trigger), the estimator (``ESTIMATE_INTERVAL_S``),
the reception reporter (``REPORT_INTERVAL_S``) and each managed subscriber (following the graph)
share it. It
lives in ``dbml.transports.worker`` (the transports need it and must not import the runtime);
this module keeps the runtime's name for it.
"""

from __future__ import annotations

from dbml.transports.worker import PeriodicWorker

__all__ = ["PeriodicWorker"]
