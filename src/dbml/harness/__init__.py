"""Process plumbing shared by the demo, the testbed, the benchmarks and the tests."""

from dbml.harness.processes import (
    RoleProcesses,
    emit_json,
    end_process,
    free_port,
    read_commands,
    serve_role,
    stop_on_signals,
    wait_ready,
)
from dbml.harness.rosmaster import RosMaster

__all__ = [
    "RoleProcesses",
    "RosMaster",
    "emit_json",
    "end_process",
    "free_port",
    "read_commands",
    "serve_role",
    "stop_on_signals",
    "wait_ready",
]
