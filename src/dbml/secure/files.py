"""``dbml secure init``'s files: the CA, and per node a key, a certificate and a zenoh config.

Nothing is replaced unless asked (``force``); every file is written atomically with its final
mode from the start, so a key is never readable by others, not even for a moment.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

from dbml.secure import pki
from dbml.secure.config import NodeFiles, zenoh_config
from dbml.secure.fleet import Fleet, FleetNode, SecureError

__all__ = ["CA_CERTIFICATE", "CA_KEY", "WrittenFile", "init_fleet"]

CA_KEY = "ca.key"
"""The CA's private key: whoever holds it can mint any node's identity; keep it off the fleet."""
CA_CERTIFICATE = "ca.pem"
_SHOWN_EXISTING = 3
"""An error about files in the way names this many of them."""


@dataclass(frozen=True, slots=True)
class WrittenFile:
    """One file ``init_fleet`` wrote, and whether it is a secret (mode 0600)."""

    path: Path
    description: str
    secret: bool


def _write(path: Path, data: bytes, *, secret: bool) -> None:
    """Write atomically with the final mode from the start: a key is never readable by others."""
    fd, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(fd, "wb") as file:
            os.fchmod(file.fileno(), 0o600 if secret else 0o644)
            file.write(data)
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def _config_text(fleet: Fleet, node: FleetNode, files: NodeFiles) -> str:
    header = (
        f"// zenoh config of dbml node {node.name!r} ({node.role.value}), "
        "written by `dbml secure init`.\n"
        f"// Use it as: dbml ... --zenoh-config {files.certificate.with_suffix('.json5')} "
        f"--host {node.name}\n"
        "// (the host identity must equal the certificate's name, or the graph rules refuse it).\n"
    )
    return header + json.dumps(zenoh_config(fleet, node.name, files), indent=2) + "\n"


def init_fleet(
    directory: str | Path,
    fleet: Fleet,
    *,
    force: bool = False,
    days: int = pki.DEFAULT_DAYS,
    install_dir: str | Path | None = None,
    now: dt.datetime | None = None,
) -> tuple[WrittenFile, ...]:
    """Write the CA, every node's key, certificate and zenoh config into ``directory``.

    Nothing is written when one of the files exists already, unless ``force``. The configs name
    the TLS files under ``install_dir`` (default: ``directory``, absolute): where the files
    will be on the nodes. Keys are written with mode 0600, the rest 0644.
    """
    if isinstance(days, bool) or not isinstance(days, int) or days < 1:
        raise SecureError(f"days={days!r} must be a whole number of days >= 1")
    target = Path(directory)
    installed = Path(install_dir) if install_dir is not None else target.resolve()
    if not installed.is_absolute():
        raise SecureError(f"install_dir={str(install_dir)!r} must be an absolute path")
    if target.exists() and not target.is_dir():
        raise SecureError(f"directory={str(target)!r} exists and is not a directory")
    names = [CA_KEY, CA_CERTIFICATE]
    for node in fleet.nodes:
        names += [f"{node.name}.key", f"{node.name}.pem", f"{node.name}.json5"]
    existing = [name for name in names if (target / name).exists()]
    if existing and not force:
        shown = ", ".join(existing[:_SHOWN_EXISTING])
        if existing[_SHOWN_EXISTING:]:
            shown += f" and {len(existing) - _SHOWN_EXISTING} more"
        raise SecureError(
            f"directory={str(target)!r} already holds {shown}: "
            "pass --force to replace them (and every node's identity)"
        )
    try:
        target.mkdir(mode=0o700, parents=True, exist_ok=True)
        return _write_fleet(target, installed, fleet, days=days, now=now)
    except OSError as err:
        raise SecureError(f"directory={str(target)!r}: {err}") from err


def _write_fleet(
    target: Path, installed: Path, fleet: Fleet, *, days: int, now: dt.datetime | None
) -> tuple[WrittenFile, ...]:
    now = now or dt.datetime.now(dt.UTC)
    ca_key = pki.new_key()
    ca = pki.ca_certificate(ca_key, now, days, fleet)
    written = [
        WrittenFile(target / CA_KEY, "fleet CA key: keep it off the fleet", True),
        WrittenFile(target / CA_CERTIFICATE, "fleet CA certificate: every node", False),
    ]
    _write(written[0].path, pki.pem_key(ca_key), secret=True)
    _write(written[1].path, pki.pem_certificate(ca), secret=False)
    for node in fleet.nodes:
        key = pki.new_key()
        certificate = pki.node_certificate(node, key, ca=ca, ca_key=ca_key, now=now, days=days)
        files = NodeFiles(
            installed / CA_CERTIFICATE,
            installed / f"{node.name}.pem",
            installed / f"{node.name}.key",
        )
        for path, data, what, secret in (
            (target / f"{node.name}.key", pki.pem_key(key), "key", True),
            (
                target / f"{node.name}.pem",
                pki.pem_certificate(certificate),
                f"certificate (CN={node.name}, SAN={','.join(node.sans)})",
                False,
            ),
            (
                target / f"{node.name}.json5",
                _config_text(fleet, node, files).encode(),
                f"zenoh config, listens on {node.endpoint}",
                False,
            ),
        ):
            _write(path, data, secret=secret)
            written.append(WrittenFile(path, f"{node.role.value} {node.name}: {what}", secret))
    return tuple(written)
