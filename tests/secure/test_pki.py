"""The fleet's certificates: every node's chains to the fleet CA and names the node."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from dbml.secure import CA_CERTIFICATE, init_fleet
from tests.secure.conftest import NODES, certificate, expiry, issued_by, sans, small_fleet


def test_every_node_certificate_chains_to_the_fleet_ca(fleet_dir: Path, tmp_path: Path) -> None:
    ca = certificate(fleet_dir / CA_CERTIFICATE)
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    assert issued_by(ca, ca)
    init_fleet(tmp_path / "other", small_fleet())
    stranger = certificate(tmp_path / "other" / "r1.pem")
    assert not issued_by(stranger, ca)  # the check can fail: another fleet's r1 is not ours
    for name in NODES:
        cert = certificate(fleet_dir / f"{name}.pem")
        assert issued_by(cert, ca)
        common_names = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
        assert [attribute.value for attribute in common_names] == [name]
        dns, ips = sans(cert)
        assert dns == [name, "localhost"]
        assert ips == ["127.0.0.1", "10.9.8.7"]
        assert not cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
        usages = cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
        assert set(usages) == {ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH}
        key = serialization.load_pem_private_key((fleet_dir / f"{name}.key").read_bytes(), None)
        assert key.public_key().public_numbers() == cert.public_key().public_numbers()  # type: ignore[union-attr]
        assert expiry(cert) - dt.datetime.now(dt.UTC) > dt.timedelta(days=364)
