"""The command line as users and scripts drive it: JSON contracts, exit codes, one-line errors."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from dbml.cli import main

REPO = Path(__file__).resolve().parents[2]
CONFIG = """\
dbm:
  max_bandwidth_in_mbit: {mbit}
  strategy: {strategy}
channels:
  - topic: /r1/camera
    frequency: {{min: 1, max: 16}}
    message_size_in_bytes: 84000
    priority: {p1}
  - topic: /r2/camera
    frequency: {{min: 1, max: 16}}
    message_size_in_bytes: 21000
    priority: {p2}
"""


def write(
    tmp_path: Path, *, mbit: float = 11, strategy: str = "paper", p1: float = 0.0, p2: float = 0.0
) -> Path:
    path = tmp_path / "config.yaml"
    path.write_text(CONFIG.format(mbit=mbit, strategy=strategy, p1=p1, p2=p2))
    return path


def run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_allocate_json_contract(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run(capsys, "allocate", str(write(tmp_path, p2=10 / 17)), "--json")
    assert code == 0
    assert err == ""
    document = json.loads(out)  # exactly one JSON object, nothing else on stdout
    assert set(document) == {
        "strategy",
        "status",
        "message",
        "budget_bytes_per_s",
        "total_bytes_per_s",
        "channels",
    }
    assert document["strategy"] == "paper"
    assert document["status"] == "optimal"
    assert document["budget_bytes_per_s"] == 1_375_000
    assert document["total_bytes_per_s"] == pytest.approx(1_375_000)
    r1, r2 = document["channels"]
    assert set(r1) == {
        "topic",
        "priority",
        "normalized_priority",
        "floor_hz",
        "rate_hz",
        "bytes_per_s",
        "share",
    }
    assert [r1["topic"], r2["topic"]] == ["/r1/camera", "/r2/camera"]
    assert round(r1["rate_hz"], 2) == 12.37
    assert r2["rate_hz"] == 16
    assert round(r1["share"], 4) == 0.7556  # bytes/s over the link's full 1,375,000 B/s
    assert r2["floor_hz"] == 16
    assert r2["normalized_priority"] == 1


def test_allocate_strategy_override(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run(capsys, "allocate", str(write(tmp_path)), "--strategy", "fair", "--json")
    assert code == 0
    document = json.loads(out)
    assert document["strategy"] == "fair"
    assert [round(c["rate_hz"], 2) for c in document["channels"]] == [13.1, 13.1]


def test_allocate_table(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run(capsys, "allocate", str(write(tmp_path, p2=10 / 17)))
    assert code == 0
    assert "/r1/camera" in out
    assert "12.37" in out
    assert "75.56%" in out
    assert "optimal" in out


def test_allocate_infeasible_exits_3_and_still_prints(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out, _ = run(capsys, "allocate", str(write(tmp_path, mbit=0.5)), "--json")
    assert code == 3
    document = json.loads(out)
    assert document["status"] == "infeasible"
    assert (
        "minimum rates need 0.840 Mbit/s but the budget allows 0.500 Mbit/s" in document["message"]
    )
    assert document["total_bytes_per_s"] <= document["budget_bytes_per_s"] * (1 + 1e-12)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (
            CONFIG.format(mbit=11, strategy="paper", p1=0, p2=0).replace(
                "priority: 0\n", "priorty: 0\n", 1
            ),
            "unknown key 'priorty'",
        ),
        (
            CONFIG.format(mbit=-3, strategy="paper", p1=0, p2=0),
            "max_bandwidth_in_mbit=-3 must be > 0",
        ),
        (
            CONFIG.format(mbit=11, strategy="paper", p1=7, p2=0),
            "channel '/r1/camera': priority=7.0 must be within [0, 1]",
        ),
        ("dbm: {max_bandwidth_in_mbit: 11\n", "invalid YAML"),
    ],
)
def test_bad_input_one_line_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], content: str, message: str
) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(content)
    code, out, err = run(capsys, "allocate", str(path), "--json")
    assert code == 2
    assert out == ""
    assert message in err
    assert err.count("\n") == 1
    assert "Traceback" not in err
    assert path.read_text() == content  # nothing lost or corrupted


def test_missing_file_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "nope.yaml"
    code, _, err = run(capsys, "allocate", str(missing))
    assert code == 2
    assert err == f"dbml: error: config '{missing}': cannot read: No such file or directory\n"


def test_usage_errors_are_one_line_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["allocate", "x.yaml", "--strategy", "magic"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "invalid choice: 'magic'" in err
    assert err.count("\n") == 1


def test_reproduce_json_matches_paper_and_has_the_contract(
    capsys: pytest.CaptureFixture[str],
) -> None:
    code, out, _ = run(capsys, "reproduce", "table2", "--json")
    assert code == 0
    document = json.loads(out)
    steps = document["steps"]
    assert [s["step"] for s in steps] == list(range(1, 11))
    assert document["all_match"] is True
    for step in steps:
        assert [r["robot"] for r in step["robots"]] == ["R1", "R2"]
        for robot in step["robots"]:
            assert {"robot", "tc_s", "priority", "rate_hz", "share"} <= set(robot)
    # tc = infinity is null (step 4, R2 stopped)
    assert steps[3]["robots"][1]["tc_s"] is None
    assert steps[3]["robots"][1]["rate_hz"] == pytest.approx(31_000 / 21_000)


def test_console_script_runs_in_a_real_process(tmp_path: Path) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "dbml", "allocate", str(write(tmp_path, p2=1.0)), "--json"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout)["channels"][1]["rate_hz"] == 16
    bad = subprocess.run(
        [sys.executable, "-m", "dbml", "allocate", str(tmp_path / "missing.yaml")],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert bad.returncode == 2
    assert bad.stderr.count("\n") == 1
    assert "Traceback" not in bad.stderr


def test_example_config_in_repo_allocates(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run(capsys, "allocate", str(REPO / "examples" / "teleop.yaml"), "--json")
    assert code == 0
    assert [round(c["rate_hz"], 2) for c in json.loads(out)["channels"]] == [12.37, 16.0]


def test_strategy_flag_overrides_the_config_before_links_are_checked(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "links.yaml"
    text = CONFIG.format(mbit=11, strategy="paper", p1=0.0, p2=0.0).replace(
        "  strategy: paper\n", ""
    )
    path.write_text(
        text + "links:\n  - {name: r1-up, max_bandwidth_in_mbit: 4, channels: [/r1/camera]}\n"
    )
    code, _, err = run(capsys, "allocate", str(path), "--json")
    assert code == 2  # the file alone asks for links under the default strategy, paper
    assert err.strip().endswith("links need strategy 'lp', but dbm.strategy='paper'")
    code, out, err = run(capsys, "allocate", str(path), "--strategy", "lp", "--json")
    assert (code, err) == (0, "")
    document = json.loads(out)
    assert document["strategy"] == "lp"
    r1 = next(c for c in document["channels"] if c["topic"] == "/r1/camera")
    assert r1["bytes_per_s"] == pytest.approx(4 * 125_000)  # the link, not the 11 Mbit budget


HZ = ("--min-hz", "1", "--max-hz", "16")


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (
            ["publish", "/r1/camera", "--size-bytes", "10000000000", *HZ],
            "--size-bytes=10000000000 must be <= 1e+09",
        ),
        (["publish", "/r1/camera/optimized", "--size-bytes", "10", *HZ], "is reserved"),
        (["publish", "/dbm/x", "--size-bytes", "10", *HZ], "is reserved"),
        (["priority", "", "0.5"], "topic=''"),
        (["priority", "/r1/camera", "nan"], "priority=nan"),
        (["priority", "/r1/camera", "1e400"], "priority=inf"),
        (["priority", "/r1/camera", "0.5", "--host", ""], "host=''"),
        (["priority", "/r1/camera", "0.5", "--connect", "tcp/127.0.0.1:99999"], "99999"),
        (["budget", "-3"], "/dbm/max_bandwidth_in_mbit=-3"),
        (["budget", "1e400"], "/dbm/max_bandwidth_in_mbit=inf"),
        (["budget", "11", "--utilization", "1.5"], "/dbm/max_bandwidth_utilization=1.5"),
        (["foxglove", "layout", "--camera", "/r1/camera/optimized"], "is reserved"),
        (["foxglove", "layout", "--channel", "r1"], "topic='r1'"),
        (["monitor", "--foxglove", "host:"], "--foxglove='host:' must be [HOST:]PORT"),
        (["optimizer", "--foxglove", "70000"], "--foxglove='70000': the port must be in"),
        (["optimizer", "--lifecycle"], "--lifecycle: a ROS 2 managed node, over --transport rclpy"),
        (["monitor", "--record", "/nonexistent/dir/v.mcap"], "directory '/nonexistent/dir'"),
        (["demo", "teleop", "--record", "/"], "--record='/' is a directory"),
        (
            ["demo", "teleop", "--transport", "rclpy", "--foxglove", "0"],
            "--foxglove/--record with --transport='rclpy'",
        ),
        (
            ["testbed", "teleop", "--transport", "rclpy", "--foxglove", "0"],
            "--foxglove/--record with --transport rclpy",
        ),
    ],
)
def test_bad_command_lines_are_one_line_exit_2(
    capsys: pytest.CaptureFixture[str], argv: list[str], message: str
) -> None:
    """Each of these once gave a traceback, ran isolated with exit 0, or wrote a bad name."""
    code, out, err = run(capsys, *argv)
    assert code == 2
    assert out == ""
    assert message in err
    assert err.count("\n") == 1
    assert "Traceback" not in err


def test_the_foxglove_layout_shows_the_cameras_and_plots_the_channels(
    capsys: pytest.CaptureFixture[str],
) -> None:
    code, out, err = run(capsys, "foxglove", "layout")
    assert (code, err) == (0, "")
    layout = json.loads(out)
    cameras = {c.get("cameraTopic") for c in layout["configById"].values()}
    assert {"/r1/camera/optimized", "/r2/camera/optimized"} <= cameras
    code, out, _ = run(capsys, "foxglove", "layout", "--camera", "/a/cam", "--channel", "/b/lidar")
    text = json.dumps(json.loads(out))
    assert "/a/cam/optimized" in text
    assert "/b/lidar/dbm/frequency/current_value.data" in text
    assert "/r1/camera" not in text
