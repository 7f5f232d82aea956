"""The teleoperation experiment that the demo and the testbed both run.

``roles`` (optimizer, robots, operator), ``runner`` (start them, collect the operator's
reports) and ``analysis`` (pure: per step, over time, after each link change). The demo and the
testbed differ only in the network the roles run on and in how they judge the result.
"""

from dbml.experiment.analysis import Analysis, Arrival, StepResult, Tick, Window, analyse
from dbml.experiment.runner import Recording, Snapshot, run_experiment
from dbml.experiment.spec import ROLES, RoleSpec

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
