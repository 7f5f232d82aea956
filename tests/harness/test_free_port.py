"""free_port: a port the kernel cannot hand to another socket before the caller binds it."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest

from dbml.harness import processes
from dbml.harness.processes import LOWEST_PORT, free_port


def _bindable(port: int) -> bool:
    with socket.socket() as sock:
        try:
            sock.bind(("127.0.0.1", port))
        except OSError:
            return False
        return True


@pytest.mark.skipif(
    not processes.EPHEMERAL_RANGE_FILE.exists(), reason="the kernel says no ephemeral range"
)
def test_a_port_below_the_kernels_own_range_and_free() -> None:
    low = int(processes.EPHEMERAL_RANGE_FILE.read_text().split()[0])
    ports = [free_port() for _ in range(50)]
    assert all(LOWEST_PORT <= p < low for p in ports), ports
    assert all(_bindable(p) for p in ports)
    assert len(set(ports)) > 40  # spread, so two runs side by side seldom pick the same


def test_a_taken_port_is_not_offered(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        # a range of one port, taken: the kernel's choice instead
        range_file = tmp_path / "range"
        range_file.write_text(f"{port + 1}\t60999\n")
        monkeypatch.setattr(processes, "EPHEMERAL_RANGE_FILE", range_file)
        monkeypatch.setattr(processes, "LOWEST_PORT", port)
        offered = free_port()
        assert offered != port
        assert _bindable(offered)


def test_without_a_known_range_the_kernel_chooses(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setattr(processes, "EPHEMERAL_RANGE_FILE", tmp_path / "absent")
    assert _bindable(free_port())
