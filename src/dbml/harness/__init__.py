"""Process plumbing shared by the demo, the testbed, the benchmarks and the tests.

``supervisor`` (the parent's side: start children, read them through one ``mailbox``, end them
by PID) and ``child`` (the child's side: its reports, its control lines, a role's protocol).
"""

from dbml.harness.child import Control, RoleError, emit_json, serve_role, stop_on_signals
from dbml.harness.mailbox import Line
from dbml.harness.processes import foreign_interpreter_env, free_port
from dbml.harness.rosmaster import RosMaster
from dbml.harness.supervisor import ChildExitedError, Supervisor

__all__ = [
    "ChildExitedError",
    "Control",
    "Line",
    "RoleError",
    "RosMaster",
    "Supervisor",
    "emit_json",
    "foreign_interpreter_env",
    "free_port",
    "serve_role",
    "stop_on_signals",
]
