"""``pip install dbml`` without its extras: the core commands work, the others name their extra.

Each case runs in a fresh interpreter where the optional packages cannot be imported (``None``
in ``sys.modules``, as for a package that is not installed), so a module-level import of one
anywhere on the path of a command fails it here.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from dbml.core.errors import DbmlError, MissingExtraError
from dbml.core.extras import EXTRAS, require

REPO = Path(__file__).resolve().parents[1]
OPTIONAL = (
    "matplotlib",
    "cryptography",
    "rclpy",
    "rosbags",
    "zenoh_ros2_sdk",
    "foxglove",
    "mcap",
    "simplejpeg",
)
"""What the extras bring, by the names they are imported as."""
WITHOUT_EXTRAS = f"import sys\nfor name in {OPTIONAL!r}:\n    sys.modules[name] = None\n"
DBML = WITHOUT_EXTRAS + "from dbml.cli import main\nsys.exit(main(sys.argv[1:]))\n"
PATH = [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]


def run(code: str, *argv: str, cwd: Path = REPO) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", code, *argv],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=cwd,
        check=False,
    )


def installing(what: str, package: str, extra: str) -> str:
    return (
        f"dbml: error: {what} needs {package}, which {sys.executable} cannot import: "
        f"pip install 'dbml[{extra}]'\n"
    )


def test_the_library_imports_and_allocates_without_extras() -> None:
    code = WITHOUT_EXTRAS + (
        "import dbml, dbml.cli.main, dbml.core.extras\n"
        "c = dbml.ChannelSpec('/c', min_rate_hz=1, max_rate_hz=2, size_bytes=10, priority=0)\n"
        "print(dbml.allocate(dbml.Problem((c,), bandwidth_mbit=1)).status.value)\n"
    )
    result = run(code)
    assert (result.returncode, result.stdout, result.stderr) == (0, "optimal\n", "")


def test_help_works_without_extras() -> None:
    result = run(DBML, "--help")
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("usage: dbml")


def test_allocate_works_without_extras() -> None:
    result = run(DBML, "allocate", "examples/teleop.yaml", "--json")
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout)["status"] == "optimal"


@pytest.mark.integration
def test_the_demo_runs_without_extras_in_every_process(tmp_path: Path) -> None:
    """The main job, live: its role processes too start without any optional package."""
    (tmp_path / "sitecustomize.py").write_text(WITHOUT_EXTRAS)  # every child imports it first
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(tmp_path), *PATH]))}
    result = subprocess.run(
        [sys.executable, "-c", DBML, "demo", "teleop", "--step-seconds", "1", "--json"],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=REPO,
        env=env,
        check=False,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert json.loads(result.stdout)["ok"] is True


def test_secure_init_names_the_secure_extra(tmp_path: Path) -> None:
    fleet = tmp_path / "fleet"
    result = run(DBML, "secure", "init", str(fleet), "--optimizer", "base", "--robots", "r1")
    assert result.returncode == 2
    assert result.stdout == ""
    assert result.stderr == installing("dbml secure init", "cryptography", "secure")
    assert not fleet.exists()


@pytest.mark.parametrize("command", ["demo", "testbed"])
def test_plot_names_the_plot_extra_before_running(command: str, tmp_path: Path) -> None:
    picture = tmp_path / "run.png"
    result = run(DBML, command, "teleop", "--json", "--plot", str(picture))
    assert result.returncode == 2
    assert result.stdout == ""
    assert result.stderr == installing("--plot", "matplotlib", "plot")
    assert not picture.exists()


@pytest.mark.parametrize(
    "argv",
    [
        ["demo", "teleop", "--json", "--foxglove", "0"],
        ["testbed", "teleop", "--json", "--record", "run.mcap"],
        ["monitor", "--foxglove", "0"],
        ["optimizer", "--record", "run.mcap"],
    ],
)
def test_the_live_view_names_the_viz_extra_before_running(argv: list[str], tmp_path: Path) -> None:
    result = run(DBML, *argv, cwd=tmp_path)
    assert result.returncode == 2
    assert result.stdout == ""
    assert result.stderr == installing("--foxglove and --record", "foxglove-sdk", "viz")
    assert not (tmp_path / "run.mcap").exists()


def test_the_ros2_transport_names_the_ros2_extra() -> None:
    result = run(DBML, "priority", "/r1/camera", "0.5", "--transport", "ros2")
    assert result.returncode == 2
    assert result.stdout == ""
    assert result.stderr == installing("transport 'ros2'", "rosbags", "ros2")


def test_the_rclpy_transport_names_the_rclpy_extra_and_ros2s_own_install() -> None:
    result = run(DBML, "priority", "/r1/camera", "0.5", "--transport", "rclpy")
    assert result.returncode == 2
    assert result.stdout == ""
    assert result.stderr == installing("transport 'rclpy'", "rclpy", "rclpy").replace(
        "'\n", "' (or source your ROS 2: . /opt/ros/<distro>/setup.bash)\n"
    )


def test_the_ros2_demo_names_the_ros2_extra() -> None:
    result = run(DBML, "demo", "teleop", "--transport", "ros2", "--json")
    assert result.returncode == 2
    assert result.stdout == ""
    assert result.stderr.count("\n") == 1
    assert result.stderr.endswith("cannot import: pip install 'dbml[ros2]'\n")


def test_require_returns_the_module() -> None:
    assert require("json", extra="plot", what="a test") is json


def test_require_names_what_needs_the_module_and_the_extra(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    with pytest.raises(MissingExtraError) as caught:
        require("matplotlib.pyplot", extra="plot", what="--plot")
    error = caught.value
    assert isinstance(error, DbmlError)
    assert isinstance(error, ImportError)  # code that handles a missing module still does
    assert (error.what, error.package, error.extra) == ("--plot", "matplotlib", "plot")
    assert str(error) == installing("--plot", "matplotlib", "plot")[len("dbml: error: ") : -1]
    assert isinstance(error.__cause__, ImportError)


def test_require_names_the_package_as_pip_knows_it(monkeypatch: pytest.MonkeyPatch) -> None:
    # Both: another test of the run may have imported the submodule already.
    monkeypatch.setitem(sys.modules, "zenoh_ros2_sdk", None)
    monkeypatch.setitem(sys.modules, "zenoh_ros2_sdk.session", None)
    with pytest.raises(MissingExtraError, match=r"needs zenoh-ros2-sdk, .*'dbml\[ros2\]'$"):
        require("zenoh_ros2_sdk.session", extra="ros2", what="a peer", package="zenoh-ros2-sdk")


def test_require_refuses_an_extra_that_does_not_exist() -> None:
    with pytest.raises(
        ValueError, match=r"^extra='plots' is not one of: plot, quality, rclpy, ros2, secure, viz$"
    ):
        require("json", extra="plots", what="a test")


def test_every_extra_is_in_pyproject_and_dev_brings_them_all() -> None:
    import tomllib

    extras = tomllib.loads((REPO / "pyproject.toml").read_text())["project"][
        "optional-dependencies"
    ]
    every = f"dbml[{','.join(EXTRAS)}]"
    assert set(EXTRAS) <= set(extras)
    # dev is the ROS 1 environment's "test" (every extra but rclpy, which breaks rospy) and
    # rclpy, and colcon for the ROS 2 package (ros2/dbml_ros).
    assert extras["dev"][0] == "dbml[rclpy,test]"
    assert {d.split(">")[0] for d in extras["dev"][1:]} == {
        "colcon-core",
        "colcon-ros",
        "colcon-python-setup-py",
        "ros-ament-package",
    }
    assert f"dbml[{','.join(e for e in EXTRAS if e != 'rclpy')}]" in extras["test"]
    assert extras["all"] == [every]
