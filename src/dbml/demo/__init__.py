"""The live demo: the paper's teleoperation scenario over a real middleware (or in memory)."""

from dbml.demo.runner import DemoOptions, DemoResult, run_teleop_demo

__all__ = ["DemoOptions", "DemoResult", "run_teleop_demo"]
