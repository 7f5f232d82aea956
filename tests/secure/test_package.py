"""``dbml.secure`` keeps the names it had as one module, sorted, each importable."""

from __future__ import annotations

import dbml.secure

PUBLIC = [
    "CA_CERTIFICATE",
    "CA_KEY",
    "DEFAULT_BASE_PORT",
    "DEFAULT_DAYS",
    "Fleet",
    "FleetNode",
    "NodeFiles",
    "NodeRole",
    "SecureError",
    "WrittenFile",
    "access_control",
    "fleet_from_flags",
    "init_fleet",
    "plan_fleet",
    "zenoh_config",
]


def test_the_package_exports_the_module_s_names_sorted() -> None:
    assert dbml.secure.__all__ == PUBLIC
    assert all(hasattr(dbml.secure, name) for name in PUBLIC)
