"""``dbml secure init``'s files: their modes, what is kept, and the command's report."""

from __future__ import annotations

import datetime as dt
import stat
from pathlib import Path

import pytest

from dbml.cli import main
from dbml.secure import CA_CERTIFICATE, CA_KEY, SecureError, init_fleet
from tests.secure.conftest import NODES, certificate, expiry, issued_by, small_fleet


def test_keys_are_private_and_the_rest_readable(fleet_dir: Path) -> None:
    modes = {path.name: stat.S_IMODE(path.stat().st_mode) for path in fleet_dir.iterdir()}
    assert len(modes) == 2 + 3 * len(NODES)  # no temporary file left behind
    for name, mode in modes.items():
        assert mode == (0o600 if name.endswith(".key") else 0o644), name
    assert stat.S_IMODE(fleet_dir.stat().st_mode) == 0o700  # created here: it holds the CA key


def test_existing_files_are_kept_unless_forced(fleet_dir: Path) -> None:
    before = {path.name: path.read_bytes() for path in fleet_dir.iterdir()}
    with pytest.raises(SecureError, match=r"already holds ca\.key, ca\.pem, opt\.key and 11 more"):
        init_fleet(fleet_dir, small_fleet())
    assert {path.name: path.read_bytes() for path in fleet_dir.iterdir()} == before
    (fleet_dir / CA_KEY).chmod(0o644)  # a forced rewrite makes a loosened key private again
    init_fleet(fleet_dir, small_fleet(), force=True)
    assert (fleet_dir / CA_KEY).read_bytes() != before[CA_KEY]
    assert stat.S_IMODE((fleet_dir / CA_KEY).stat().st_mode) == 0o600
    assert issued_by(certificate(fleet_dir / "r1.pem"), certificate(fleet_dir / CA_CERTIFICATE))


def test_bad_days_and_a_file_in_the_way(tmp_path: Path) -> None:
    with pytest.raises(SecureError, match="days=0 must be a whole number of days >= 1"):
        init_fleet(tmp_path / "a", small_fleet(), days=0)
    (tmp_path / "file").write_text("")
    with pytest.raises(SecureError, match="exists and is not a directory"):
        init_fleet(tmp_path / "file", small_fleet())


def test_the_cli_writes_and_reports(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["secure", "init", str(tmp_path / "f"), "--optimizer", "opt", "--robots", "r1,r2"]
    argv += ["--operators", "op", "--endpoint", "r1=tls/10.0.0.5:7447", "--days", "30"]
    assert main(argv) == 0
    out, err = capsys.readouterr()
    assert err == ""
    lines = out.splitlines()
    assert len(lines) == 2 + 3 * 4 + 1
    assert f"wrote {tmp_path / 'f' / 'r1.key'} (0600): robot r1: key" in lines
    assert any("r1.json5" in line and "tls/10.0.0.5:7447" in line for line in lines)
    assert "--zenoh-config" in lines[-1]
    assert "--host NAME" in lines[-1]
    assert expiry(certificate(tmp_path / "f" / "r1.pem")) - dt.datetime.now(dt.UTC) < (
        dt.timedelta(days=31)
    )
    assert main(argv) == 2  # files in the way: one line, nothing touched
    out, err = capsys.readouterr()
    assert out == ""
    assert err.count("\n") == 1
    assert "--force" in err
    assert main([*argv, "--force"]) == 0


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--robots", "r1,,r2"], "dbml: error: --robots='r1,,r2' has an empty name\n"),
        (["--robots", "r1", "--operators", "r1"], "dbml: error: name 'r1' appears twice"),
        (["--robots", "r 1"], "dbml: error: robots='r 1' must be a letter"),
    ],
)
def test_the_cli_refuses_bad_input_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], flags: list[str], message: str
) -> None:
    assert main(["secure", "init", str(tmp_path / "f"), "--optimizer", "opt", *flags]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err.startswith(message)
    assert err.count("\n") == 1
    assert not (tmp_path / "f").exists()
