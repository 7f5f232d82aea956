"""The fleet from ``dbml secure init``'s flags, and every bad flag named with its value."""

from __future__ import annotations

import pytest

from dbml.secure import DEFAULT_BASE_PORT, NodeRole, SecureError, fleet_from_flags


def test_endpoint_hosts_and_extra_names_go_into_the_certificate_names() -> None:
    fleet = fleet_from_flags(
        optimizer="opt",
        robots="r1, r2",
        operators="op",
        endpoints=["r1=tls/10.200.1.2:7447", "op=tls/op.lan:7447", "r2=tls/[fd00::2]:7447"],
        sans=["192.168.1.9", "r1=r1.lan", "r1=10.0.0.7"],
    )
    r1, r2, op = fleet.node("r1"), fleet.node("r2"), fleet.node("op")
    assert r1.endpoint == "tls/10.200.1.2:7447"
    assert r1.sans == (
        "r1",
        "localhost",
        "127.0.0.1",
        "10.200.1.2",
        "192.168.1.9",
        "r1.lan",
        "10.0.0.7",
    )
    assert "fd00::2" in r2.sans
    assert op.sans == ("op", "localhost", "127.0.0.1", "op.lan", "192.168.1.9")
    assert fleet.node("opt").endpoint == f"tls/127.0.0.1:{DEFAULT_BASE_PORT}"
    assert (
        fleet_from_flags(optimizer="opt", robots="r1", operators="").of_role(NodeRole.OPERATOR)
        == ()
    )


@pytest.mark.parametrize(
    ("flags", "match"),
    [
        ({"optimizer": ""}, "optimizer='': a node name must not be empty"),
        ({"robots": "r1,,r2"}, "--robots='r1,,r2' has an empty name"),
        ({"robots": ""}, r"robots=\[\]: a fleet needs at least one robot"),
        ({"operators": "op,"}, "--operators='op,' has an empty name"),
        ({"robots": "r1,R1"}, "name 'R1' appears twice"),
        ({"operators": "r2"}, "name 'r2' appears twice"),
        ({"robots": "r_1"}, "robots='r_1' must be a letter"),
        ({"robots": "r1/cam"}, "robots='r1/cam' must be a letter"),
        ({"robots": "r*"}, r"robots='r\*' must be a letter"),
        ({"robots": "1r"}, "robots='1r' must be a letter"),
        ({"robots": "r-"}, "robots='r-' must be a letter"),
        ({"robots": "r" * 64}, "must be a letter"),
        ({"robots": "dbml"}, "robots='dbml' is reserved"),
        ({"optimizer": "DBM"}, "optimizer='DBM' is reserved"),
        ({"operators": "ca"}, "operators='ca' is reserved"),
        ({"endpoints": ["r1"]}, "--endpoint='r1' must look like NAME=VALUE"),
        ({"endpoints": ["r1=tcp/10.0.0.1:7447"]}, r"endpoint\[r1\]='tcp/10.0.0.1:7447' must look"),
        ({"endpoints": ["r1=tls/10.0.0.1"]}, r"endpoint\[r1\]='tls/10.0.0.1' must look"),
        ({"endpoints": ["r1=tls/10.0.0.1:0"]}, "port 1-65535"),
        ({"endpoints": ["r1=tls/10.0.0.1:70000"]}, "port 1-65535"),
        ({"endpoints": ["r1=tls/0.0.0.0:7447"]}, "not a wildcard"),
        ({"endpoints": ["r1=tls/bad_host:7447"]}, "must be an IP address or a DNS name"),
        ({"endpoints": ["r3=tls/10.0.0.1:7447"]}, "endpoint for 'r3': no such node"),
        (
            {"endpoints": ["r1=tls/10.0.0.1:7447", "r1=tls/10.0.0.2:7447"]},
            "'r1' has an endpoint already",
        ),
        (
            {"endpoints": ["r1=tls/10.0.0.1:7447", "r2=tls/10.0.0.1:7447"]},
            r"endpoint\[r2\]='tls/10.0.0.1:7447' is also the endpoint of 'r1'",
        ),
        ({"sans": ["not a name"]}, "san='not a name' must be an IP address or a DNS name"),
        ({"sans": ["r1=a..b"]}, r"san\[r1\]='a..b' must be an IP address"),
        ({"sans": ["nobody=10.0.0.1"]}, "san for 'nobody': no such node"),
        ({"base_port": 0}, "base_port=0 must be 1-65532"),
        ({"base_port": 65534}, "base_port=65534 must be 1-65532"),
    ],
)
def test_bad_input_names_the_field_and_the_value(flags: dict[str, object], match: str) -> None:
    arguments: dict[str, object] = {"optimizer": "opt", "robots": "r1,r2", "operators": "op"}
    arguments.update(flags)
    with pytest.raises(SecureError, match=match):
        fleet_from_flags(**arguments)  # type: ignore[arg-type]
