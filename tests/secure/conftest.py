"""A small fleet for every test of ``dbml.secure``, its files, and what their certificates say."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives.asymmetric import ec

from dbml.secure import Fleet, init_fleet, plan_fleet

NODES = ("opt", "r1", "r2", "op")


def small_fleet(**options: object) -> Fleet:
    return plan_fleet(optimizer="opt", robots=["r1", "r2"], operators=["op"], **options)  # type: ignore[arg-type]


@pytest.fixture
def fleet_dir(tmp_path: Path) -> Path:
    init_fleet(tmp_path / "fleet", small_fleet(sans=["10.9.8.7"]))
    return tmp_path / "fleet"


def certificate(path: Path) -> x509.Certificate:
    return x509.load_pem_x509_certificate(path.read_bytes())


def issued_by(cert: x509.Certificate, ca: x509.Certificate) -> bool:
    public = ca.public_key()
    assert isinstance(public, ec.EllipticCurvePublicKey)
    algorithm = cert.signature_hash_algorithm
    assert algorithm is not None
    try:
        public.verify(cert.signature, cert.tbs_certificate_bytes, ec.ECDSA(algorithm))
    except InvalidSignature:
        return False
    return cert.issuer == ca.subject


def sans(cert: x509.Certificate) -> tuple[list[str], list[str]]:
    extension = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    ips = [str(ip) for ip in extension.get_values_for_type(x509.IPAddress)]
    return extension.get_values_for_type(x509.DNSName), ips


def expiry(cert: x509.Certificate) -> dt.datetime:
    # newer cryptography deprecates the naive attribute (and warnings are errors here)
    aware: dt.datetime | None = getattr(cert, "not_valid_after_utc", None)
    return aware if aware is not None else cert.not_valid_after.replace(tzinfo=dt.UTC)
