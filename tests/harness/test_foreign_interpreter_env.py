"""A child that another interpreter runs inherits none of the ROS 2 wheels' bootstrap."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

from dbml.harness.processes import foreign_interpreter_env

GUARD = "_ROS_WHEELS_BOOTSTRAP_COMPLETE"
DEBIAN_PYTHON = Path("/usr/bin/python3")
SHOW = "import os; print(os.environ.get('_ROS_WHEELS_BOOTSTRAP_COMPLETE'));"
SHOW += "print(os.environ.get('LD_LIBRARY_PATH'))"


def test_the_guard_and_the_bootstraps_library_path_go_and_the_rest_stays(tmp_path: Path) -> None:
    other_venv = tmp_path / "venv"
    (other_venv / "lib").mkdir(parents=True)
    (other_venv / "pyvenv.cfg").write_text("home = /usr/bin\n")
    version = f"python{sys.version_info.major}.{sys.version_info.minor}"
    wheels = f"{sys.prefix}/lib/{version}/site-packages/ros_rcl.libs"
    added = [f"{sys.prefix}/lib", wheels, str(other_venv / "lib")]
    base = {
        GUARD: "1",
        "LD_LIBRARY_PATH": os.pathsep.join(added),
        "PATH": "/usr/bin:/bin",
        "ROS_MASTER_URI": "http://127.0.0.1:11311/",
    }
    assert foreign_interpreter_env(base) == {
        "PATH": "/usr/bin:/bin",
        "ROS_MASTER_URI": "http://127.0.0.1:11311/",
    }
    assert base[GUARD] == "1"  # a copy: the caller's mapping is untouched
    own = os.pathsep.join(["/opt/ros/noetic/lib", *added, "/usr/local/cuda/lib64"])
    kept = foreign_interpreter_env({GUARD: "1", "LD_LIBRARY_PATH": own})
    assert kept == {"LD_LIBRARY_PATH": "/opt/ros/noetic/lib:/usr/local/cuda/lib64"}


def test_the_default_is_this_processs_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(GUARD, "1")
    monkeypatch.setenv("DBML_TEST_MARK", "kept")
    env = foreign_interpreter_env()
    assert GUARD not in env
    assert env["DBML_TEST_MARK"] == "kept"


@pytest.mark.skipif(not DEBIAN_PYTHON.exists(), reason="no /usr/bin/python3 on this machine")
def test_debians_python_started_with_it_sees_no_bootstrap() -> None:
    if importlib.util.find_spec("ros_wheels_bootstrapper") is not None:
        # The main environment: its bootstrap re-executed this very process with the guard set.
        assert os.environ.get(GUARD) == "1"
        parent = dict(os.environ)
    else:  # the ROS 1 environment: as if started from the main one without this hygiene
        parent = dict(os.environ, **{GUARD: "1"})

    def child(env: dict[str, str]) -> list[str]:
        argv = [str(DEBIAN_PYTHON), "-c", SHOW]
        done = subprocess.run(
            argv, env=env, capture_output=True, text=True, timeout=60, check=False
        )
        assert done.returncode == 0, done.stderr
        return done.stdout.splitlines()

    assert child(parent)[0] == "1"  # what it would inherit without the hygiene
    guard, library_path = child(foreign_interpreter_env(parent))
    assert guard == "None"
    entries = [] if library_path == "None" else library_path.split(os.pathsep)
    prefix = Path(sys.prefix).resolve()
    leaked = [e for e in entries if Path(e).resolve().is_relative_to(prefix) or "/ros_" in e]
    assert leaked == []
