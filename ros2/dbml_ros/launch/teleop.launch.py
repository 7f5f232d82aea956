"""The paper's teleoperation: the optimizer, and one bridge per robot in its namespace."""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

ROBOTS = ("r1", "r2")


def generate_launch_description() -> LaunchDescription:
    """What ``ros2 launch dbml_ros teleop.launch.py [params_file:=FILE]`` starts."""
    default = os.path.join(get_package_share_directory("dbml_ros"), "config", "teleop.yaml")
    params_file = LaunchConfiguration("params_file")
    return LaunchDescription(
        [
            DeclareLaunchArgument("params_file", default_value=default),
            Node(
                package="dbml_ros",
                executable="optimizer",
                name="dbml_optimizer",
                parameters=[params_file],
                output="screen",
            ),
            *(
                Node(
                    package="dbml_ros",
                    executable="bridge",
                    name="dbml_bridge",
                    namespace=robot,
                    parameters=[params_file],
                    output="screen",
                )
                for robot in ROBOTS
            ),
        ]
    )
