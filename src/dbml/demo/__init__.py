"""The live demo: the paper's teleoperation scenario over a real middleware (or in memory)."""

from dbml.demo.runner import DemoResult, run_teleop_demo

__all__ = ["DemoResult", "run_teleop_demo"]
