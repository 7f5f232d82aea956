"""Each node's zenoh config: zenoh parses it, and it names the node's own TLS files."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import zenoh

from dbml.secure import CA_CERTIFICATE, SecureError, access_control, init_fleet
from tests.secure.conftest import small_fleet


def test_configs_parse_and_name_the_node_s_files(fleet_dir: Path) -> None:
    fleet = small_fleet(sans=["10.9.8.7"])
    for node in fleet.nodes:
        config = zenoh.Config.from_file(str(fleet_dir / f"{node.name}.json5"))
        tls = json.loads(config.get_json("transport/link/tls"))
        assert tls["enable_mtls"] is True
        assert tls["verify_name_on_connect"] is True
        assert tls["root_ca_certificate"] == str((fleet_dir / CA_CERTIFICATE).resolve())
        for side in ("listen", "connect"):
            assert tls[f"{side}_certificate"] == str((fleet_dir / f"{node.name}.pem").resolve())
            assert tls[f"{side}_private_key"] == str((fleet_dir / f"{node.name}.key").resolve())
        spare = node.endpoint.rpartition(":")[0] + ":0"  # a second process of the node
        assert json.loads(config.get_json("listen/endpoints")) == [node.endpoint, spare]
        others = [other.endpoint for other in fleet.nodes if other is not node]
        assert json.loads(config.get_json("connect/endpoints")) == others
        assert json.loads(config.get_json("transport/shared_memory/enabled")) is False
        loaded = json.loads(config.get_json("access_control"))
        # zenoh read every field: unset optional subject fields come back as null
        loaded["subjects"] = [
            {key: value for key, value in subject.items() if value is not None}
            for subject in loaded["subjects"]
        ]
        assert loaded == access_control(fleet)


def test_install_dir_is_what_the_configs_name(tmp_path: Path) -> None:
    init_fleet(tmp_path / "out", small_fleet(), install_dir="/etc/dbml")
    config = zenoh.Config.from_file(str(tmp_path / "out" / "r1.json5"))
    assert json.loads(config.get_json("transport/link/tls/listen_private_key")) == (
        "/etc/dbml/r1.key"
    )
    with pytest.raises(SecureError, match="install_dir='etc' must be an absolute path"):
        init_fleet(tmp_path / "again", small_fleet(), install_dir="etc")
