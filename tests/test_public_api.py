import importlib
import pkgutil
import re
import subprocess
import sys
from pathlib import Path

import pytest

import dbml
from tests.conftest import require
from tests.ros1.rosnet import ros1_problem

ROS1_MODULES = ("dbml.ros1", "dbml.transports.ros1")
"""Modules that need rospy (Debian's packages): checked by ros1 tests, in .venv-ros1."""
PACKAGES = [
    "dbml",
    "dbml.cli",
    "dbml.core",
    "dbml.demo",
    "dbml.estimator",
    "dbml.experiment",
    "dbml.experiment.analysis",
    "dbml.harness",
    "dbml.protocol",
    "dbml.runtime",
    "dbml.scenarios",
    "dbml.secure",
    "dbml.testbed",
    "dbml.testing",
    "dbml.transports",
    "dbml.transports.rclpy",
    "dbml.transports.ros2",
    "dbml.transports.zenoh",
]


def need_rospy(name: str) -> None:
    """A module of ROS1_MODULES is checked where rospy imports: skipped elsewhere, CI fails."""
    if name.startswith(ROS1_MODULES):
        require(ros1_problem(), what=f"check {name}")


@pytest.mark.parametrize(
    "name",
    [
        *PACKAGES,
        *(
            pytest.param(name, marks=pytest.mark.ros1)
            for name in ("dbml.ros1", "dbml.transports.ros1")
        ),
    ],
)
def test_all_is_sorted_and_resolves(name: str) -> None:
    need_rospy(name)
    module = importlib.import_module(name)
    names = list(module.__all__)
    assert names == sorted(names, key=lambda n: (not n.isupper(), n)) or names == sorted(names)
    for item in names:
        assert hasattr(module, item), item


def test_the_top_level_is_what_a_user_needs_and_loads_the_runtime_lazily() -> None:
    assert len(dbml.__all__) <= 25
    code = (
        "import sys, dbml; loaded = sorted(m for m in sys.modules "
        "if m.startswith(('dbml.runtime', 'dbml.transports', 'zenoh')));"
        "print(','.join(loaded)); dbml.ManagedPublisher; dbml.open_transport;"
        "print('dbml.runtime.publisher' in sys.modules)"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True
    )
    assert result.stdout.splitlines() == ["", "True"]
    with pytest.raises(AttributeError, match="module 'dbml' has no attribute 'nope'"):
        _ = dbml.nope


def modules(*, ros1: bool) -> list[str]:
    """The modules of dbml: those that need rospy (ROS1_MODULES), or all the others."""
    return [
        info.name
        for info in pkgutil.walk_packages(dbml.__path__, "dbml.")
        if not info.name.endswith("__main__") and info.name.startswith(ROS1_MODULES) == ros1
    ]


@pytest.mark.parametrize(
    "ros1", [False, pytest.param(True, marks=pytest.mark.ros1)], ids=["main", "ros1"]
)
def test_every_module_declares_all(ros1: bool) -> None:
    names = modules(ros1=ros1)
    assert names
    for name in names:
        need_rospy(name)
        module = importlib.import_module(name)
        assert hasattr(module, "__all__"), name


def test_py_typed_marker_ships() -> None:
    assert (Path(dbml.__file__).parent / "py.typed").exists()


def test_readme_python_examples_run(capsys: pytest.CaptureFixture[str]) -> None:
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", readme, re.S)
    blocks = [b for b in blocks if "import rospy" not in b]  # tests/ros1 runs that one as a node
    assert len(blocks) == 3
    exec(compile(blocks[0], "README.md", "exec"), {})
    assert capsys.readouterr().out.startswith("optimal {'/r1/camera': 12.369")
    exec(compile(blocks[1], "README.md", "exec"), {})
    assert capsys.readouterr().out == "5.95\n"
    exec(compile(blocks[2], "README.md", "exec"), {})
    assert capsys.readouterr().out == "12.37 16.0\n"
