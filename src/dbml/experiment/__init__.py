"""The teleoperation experiment that the demo and the testbed both run.

``roles`` (optimizer, robots, operator), ``runner`` (start them, collect the operator's
reports) and ``analysis`` (pure: per step, over time, after each link change). The demo and the
testbed differ only in the network the roles run on and in how they judge the result. The
runner's names load on first use, so a run's child (``python -m dbml.experiment KIND``) imports
only what its kind needs.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from dbml.core.lazy import lazy_names
from dbml.experiment.analysis import Analysis, Arrival, StepResult, Tick, Window, analyse
from dbml.experiment.spec import ROLES, RoleSpec

if TYPE_CHECKING:
    from dbml.experiment.runner import Recording, Snapshot, run_experiment

__all__ = [
    "ROLES",
    "Analysis",
    "Arrival",
    "Recording",
    "RoleSpec",
    "Snapshot",
    "StepResult",
    "Tick",
    "Window",
    "analyse",
    "run_experiment",
]

_LAZY = {
    "Recording": "dbml.experiment.runner",
    "Snapshot": "dbml.experiment.runner",
    "run_experiment": "dbml.experiment.runner",
}


__getattr__ = lazy_names(__name__, _LAZY)
