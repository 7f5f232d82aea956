"""What ``ros2 run dbml_ros <executable>`` starts: a dbml command over rclpy.

Each is ``dbml <command> --transport rclpy`` with the rest of the command line, ``--ros-args``
included, so ROS 2's arguments (``-r __ns:=``, ``-p``, ``--params-file``) reach rclpy.
"""

from __future__ import annotations

import sys

from dbml.cli import main


def _run(command: str) -> None:
    sys.exit(main([command, "--transport", "rclpy", *sys.argv[1:]]))


def optimizer() -> None:
    """``dbml optimizer``: ``/dbm``'s allocation each period."""
    _run("optimizer")


def bridge() -> None:
    """``dbml bridge``: the channels of the params file under this node's namespace."""
    _run("bridge")


def monitor() -> None:
    """``dbml monitor``: the allocation as a table."""
    _run("monitor")
