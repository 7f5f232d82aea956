"""dbml_ros: dbml's commands as ROS 2 executables, its launch files and Table 1's parameters."""

from glob import glob

from setuptools import setup

PACKAGE = "dbml_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=[PACKAGE],
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/launch", glob("launch/*")),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="dbml developers",
    maintainer_email="dbml@example.org",
    description="dbml's optimizer, bridge and monitor as ROS 2 executables",
    license="MIT",
    entry_points={
        "console_scripts": [
            f"optimizer = {PACKAGE}.executables:optimizer",
            f"bridge = {PACKAGE}.executables:bridge",
            f"monitor = {PACKAGE}.executables:monitor",
        ],
    },
)
