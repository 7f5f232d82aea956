"""``dbml secure init``: the certificates, the configs, and what zenoh enforces with them.

The integration tests open real zenoh sessions from the generated files on loopback. "Does not
arrive" is never judged by waiting: a control write that must arrive is sent after the forbidden
ones on the same session (one transport, in order), and once it is in, the forbidden ones would
have been too.
"""

from __future__ import annotations

import datetime as dt
import json
import stat
import threading
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
import zenoh
from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from dbml.cli import main
from dbml.harness.processes import free_port
from dbml.runtime import names
from dbml.runtime.estimator import LINK_TOPIC
from dbml.secure import (
    CA_CERTIFICATE,
    CA_KEY,
    DEFAULT_BASE_PORT,
    Fleet,
    NodeRole,
    SecureError,
    access_control,
    fleet_from_flags,
    init_fleet,
    plan_fleet,
)
from dbml.transports.base import Variant
from dbml.transports.paramstore import BATCH_KEY, PARAM_PREFIX
from dbml.transports.zenoh import _data_key
from tests.conftest import wait_for

NODES = ("opt", "r1", "r2", "op")


def small_fleet(**options: object) -> Fleet:
    return plan_fleet(optimizer="opt", robots=["r1", "r2"], operators=["op"], **options)  # type: ignore[arg-type]


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


# -- the plan ---------------------------------------------------------------------------------


def test_the_plan_orders_roles_and_gives_loopback_defaults() -> None:
    fleet = small_fleet(base_port=20000)
    assert fleet.names == NODES
    assert [node.role for node in fleet.nodes] == [
        NodeRole.OPTIMIZER,
        NodeRole.ROBOT,
        NodeRole.ROBOT,
        NodeRole.OPERATOR,
    ]
    assert [node.endpoint for node in fleet.nodes] == [
        f"tls/127.0.0.1:{20000 + i}" for i in range(4)
    ]
    assert fleet.node("r1").sans == ("r1", "localhost", "127.0.0.1")
    assert small_fleet().nodes[0].endpoint == f"tls/127.0.0.1:{DEFAULT_BASE_PORT}"


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


def test_one_string_is_not_a_list_of_robots() -> None:
    with pytest.raises(SecureError, match="not one string"):
        plan_fleet(optimizer="opt", robots="r1")


# -- the access control document -------------------------------------------------------------


def test_the_access_control_has_one_subject_per_node_and_unique_ids() -> None:
    document = access_control(small_fleet())
    assert document["enabled"] is True
    assert document["default_permission"] == "deny"
    assert document["subjects"] == [{"id": n, "cert_common_names": [n]} for n in NODES]
    ids = [rule["id"] for rule in document["rules"]]
    assert len(ids) == len(set(ids))
    referenced = {rule for policy in document["policies"] for rule in policy["rules"]}
    assert referenced == set(ids)
    by_id = {rule["id"]: rule for rule in document["rules"]}
    # only "egress" allows what a node sends; everything else judges what arrives
    assert [rule["id"] for rule in document["rules"] if rule["flows"] != ["ingress"]] == ["egress"]
    assert by_id["r1/put"]["key_exprs"] == ["r1/**", "dbml/param/r1/**"]
    assert by_id["r1/put-deny"]["key_exprs"] == [
        "dbml/param/r1/**/dbm/frequency/current_value",
        "dbml/param/r1/**/dbm/managed",
    ]
    assert by_id["opt/reply"]["key_exprs"] == ["dbml/own/**"]
    assert "op/put-deny" not in by_id


def test_the_rules_use_the_runtime_s_own_names() -> None:
    """The ACL spells the keys itself; this keeps it in step with the transport and names."""
    document = access_control(small_fleet())
    by_id = {rule["id"]: rule for rule in document["rules"]}
    operator, optimizer = by_id["op/put"]["key_exprs"], by_id["opt/put"]["key_exprs"]
    for name in (names.BANDWIDTH, names.UTILIZATION, names.PERIOD, names.STRATEGY):
        assert PARAM_PREFIX + name in operator
    assert f"{PARAM_PREFIX}/**/dbm/{names.PRIORITY_FIELD}" in operator
    for name in (names.STATUS, names.STATUS_MESSAGE, names.ESTIMATE, names.ESTIMATOR_STATE):
        assert PARAM_PREFIX + name in optimizer
    for field in (names.CURRENT_FIELD, names.MANAGED_FIELD):
        assert f"{PARAM_PREFIX}/**/dbm/{field}" in optimizer
        assert f"{PARAM_PREFIX}/r1/**/dbm/{field}" in by_id["r1/put-deny"]["key_exprs"]
    assert BATCH_KEY in optimizer
    # the estimator's beacon: the optimizer's node puts it, and no one else may
    link_key = _data_key(LINK_TOPIC, Variant.FULL)
    assert link_key in optimizer
    assert all(link_key not in by_id[f"{n}/put"]["key_exprs"] for n in ("r1", "r2", "op"))


# -- the files --------------------------------------------------------------------------------


@pytest.fixture
def fleet_dir(tmp_path: Path) -> Path:
    init_fleet(tmp_path / "fleet", small_fleet(sans=["10.9.8.7"]))
    return tmp_path / "fleet"


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


def test_keys_are_private_and_the_rest_readable(fleet_dir: Path) -> None:
    modes = {path.name: stat.S_IMODE(path.stat().st_mode) for path in fleet_dir.iterdir()}
    assert len(modes) == 2 + 3 * len(NODES)  # no temporary file left behind
    for name, mode in modes.items():
        assert mode == (0o600 if name.endswith(".key") else 0o644), name
    assert stat.S_IMODE(fleet_dir.stat().st_mode) == 0o700  # created here: it holds the CA key


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


# -- what zenoh enforces with the generated configs (loopback) --------------------------------


def open_node(path: Path) -> zenoh.Session:
    config = zenoh.Config.from_file(str(path))
    config.insert_json5("transport/shared_memory/enabled", "false")
    return zenoh.open(config)


class Recorder:
    """Every sample a session receives on ``**``: (key, payload)."""

    def __init__(self, session: zenoh.Session) -> None:
        self._lock = threading.Lock()
        self._seen: list[tuple[str, str]] = []
        self._subscriber = session.declare_subscriber("**", self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self._seen.append((str(sample.key_expr), sample.payload.to_bytes().decode()))

    def seen(self) -> list[tuple[str, str]]:
        with self._lock:
            return list(self._seen)


@pytest.fixture
def mesh(tmp_path: Path) -> Iterator[tuple[Path, dict[str, zenoh.Session]]]:
    """The four nodes' sessions, connected in a full mesh, from the generated configs."""
    endpoints = {name: f"tls/127.0.0.1:{free_port()}" for name in NODES}
    init_fleet(tmp_path / "fleet", small_fleet(endpoints=endpoints))
    sessions: dict[str, zenoh.Session] = {}
    try:
        for name in NODES:
            sessions[name] = open_node(tmp_path / "fleet" / f"{name}.json5")
        wait_for(
            lambda: all(len(list(s.info.peers_zid())) == 3 for s in sessions.values()),
            timeout_s=15,
            what="the full TLS mesh",
        )
        yield tmp_path / "fleet", sessions
    finally:
        for session in sessions.values():
            session.close()  # type: ignore[no-untyped-call]


def listening(recorder: Recorder, sender: zenoh.Session, probe: str) -> None:
    """Wait until ``recorder``'s subscriber is known to ``sender``: an allowed probe arrives."""

    def arrived() -> bool:
        sender.put(probe, "probe")
        return (probe, "probe") in recorder.seen()

    wait_for(arrived, timeout_s=10, what=f"{probe} to arrive")


def sent_in_order(
    sender: zenoh.Session, recorder: Recorder, keys: list[str], control: str
) -> list[str]:
    """Put every key, then the control; the keys that had arrived once the control did."""
    for key in keys:
        sender.put(key, "tried")
    sender.put(control, "control")
    wait_for(lambda: (control, "control") in recorder.seen(), timeout_s=10, what=control)
    return [key for key, payload in recorder.seen() if payload == "tried"]


ROBOT_FORBIDDEN = [
    "dbml/param/dbm/max_bandwidth_in_mbit",
    "dbml/param/r2/camera/dbm/priority",
    "dbml/param/r1/camera/dbm/frequency/current_value",  # inside r1/**: the deny rule wins
    "dbml/param/r1/camera/dbm/managed",
    "dbml/param/*/camera/dbm/priority",  # a wildcard cannot reach beyond r1's own keys
    "dbml/batch",
    "r2/camera",
    "dbml/param/dbm/status",
    "dbm/link",
]
ROBOT_ALLOWED = [
    "r1/camera",
    "r1/camera/optimized",
    "dbml/param/r1/camera/dbm/frequency/min",
    "dbml/param/r1/camera/dbm/frequency/max",
    "dbml/param/r1/camera/dbm/message_size_in_bytes",
    "dbml/param/r1/camera/dbm/frequency/applied_value",
]


@pytest.mark.integration
def test_a_robot_writes_its_own_channels_only(mesh: tuple[Path, dict[str, zenoh.Session]]) -> None:
    _, sessions = mesh
    at_optimizer = Recorder(sessions["opt"])
    listening(at_optimizer, sessions["r1"], "r1/probe")
    control = "dbml/param/r1/camera/dbm/priority"
    arrived = sent_in_order(sessions["r1"], at_optimizer, ROBOT_FORBIDDEN + ROBOT_ALLOWED, control)
    assert arrived == ROBOT_ALLOWED


@pytest.mark.integration
def test_the_optimizer_writes_its_allocation_and_status_only(
    mesh: tuple[Path, dict[str, zenoh.Session]],
) -> None:
    """The keys refused from a robot arrive from the optimizer: the refusal is the ACL's."""
    _, sessions = mesh
    at_robot = Recorder(sessions["r1"])
    listening(at_robot, sessions["opt"], "dbml/param/dbm/round")
    optimizer_keys = [
        "dbml/batch",
        "dbml/param/r1/camera/dbm/frequency/current_value",
        "dbml/param/r1/camera/dbm/managed",
        "dbml/param/dbm/status",
        "dbml/param/dbm/status_message",
        "dbml/param/dbm/estimated_bandwidth_in_mbit",
        "dbml/param/dbm/estimator_state",
        "dbm/link",
    ]
    forbidden = ["dbml/param/dbm/max_bandwidth_in_mbit", "dbml/param/r1/camera/dbm/priority"]
    forbidden += ["r1/camera", "dbml/param/r1/camera/dbm/frequency/min"]
    arrived = sent_in_order(
        sessions["opt"], at_robot, forbidden + optimizer_keys, "dbml/param/dbm/round"
    )
    assert arrived == optimizer_keys


@pytest.mark.integration
def test_an_operator_sets_the_budget_and_priorities_only(
    mesh: tuple[Path, dict[str, zenoh.Session]],
) -> None:
    _, sessions = mesh
    at_optimizer = Recorder(sessions["opt"])
    listening(at_optimizer, sessions["op"], "dbml/param/dbm/strategy")
    allowed = [
        "dbml/param/dbm/max_bandwidth_in_mbit",
        "dbml/param/dbm/max_bandwidth_utilization",
        "dbml/param/dbm/optimization_rate_in_seconds",
        "dbml/param/r1/camera/dbm/priority",
        "dbml/param/r2/camera/dbm/priority",
    ]
    forbidden = [
        "dbml/param/r1/camera/dbm/frequency/min",
        "dbml/param/r1/camera/dbm/frequency/current_value",
        "dbml/param/dbm/status",
        "dbml/batch",
        "op/camera",
        "r1/camera",
    ]
    control = "dbml/param/dbm/strategy"
    arrived = sent_in_order(sessions["op"], at_optimizer, forbidden + allowed, control)
    assert arrived == allowed


@pytest.mark.integration
def test_replies_are_refused_like_puts(mesh: tuple[Path, dict[str, zenoh.Session]]) -> None:
    _, sessions = mesh
    offered = {
        "r1": [
            "dbml/own/n1/r1/camera/dbm/priority",
            "dbml/own/n1/r1/camera/dbm/frequency/current_value",
            "dbml/own/n1/r2/camera/dbm/priority",
            "dbml/own/n1/dbm/max_bandwidth_in_mbit",
        ],
        "op": [
            "dbml/own/n2/dbm/max_bandwidth_in_mbit",
            "dbml/own/n2/r2/camera/dbm/priority",
            "dbml/own/n2/r2/camera/dbm/frequency/min",
            "dbml/own/n2/dbm/status",
        ],
        "r2": [
            "dbml/own/n3/r2/camera/dbm/frequency/max",
            "dbml/own/n3/r1/camera/dbm/frequency/max",
        ],
    }
    queryables = []
    for name, keys in offered.items():

        def serve(query: zenoh.Query, keys: list[str] = keys) -> None:
            for key in keys:
                query.reply(key, "value")

        queryables.append(sessions[name].declare_queryable("dbml/own/**", serve))

    def answers() -> set[str]:
        replies = sessions["opt"].get(
            "dbml/own/**",
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=5,
        )
        return {str(reply.ok.key_expr) for reply in replies if reply.ok is not None}

    expected = {
        "dbml/own/n1/r1/camera/dbm/priority",
        "dbml/own/n2/dbm/max_bandwidth_in_mbit",
        "dbml/own/n2/r2/camera/dbm/priority",
        "dbml/own/n3/r2/camera/dbm/frequency/max",
    }
    # a query ends when every queryable has answered: no waiting for what does not come
    wait_for(lambda: answers() == expected, timeout_s=10, what="every queryable to answer")
    assert answers() == expected
    # and what the optimizer serves (values whose writer left) reaches everyone
    queryables.append(
        sessions["opt"].declare_queryable(
            "dbml/own/**", lambda query: query.reply("dbml/own/n4/r1/camera/dbm/priority", "v")
        )
    )

    def kept() -> set[str]:
        replies = sessions["r2"].get("dbml/own/n4/**", timeout=5)
        return {str(reply.ok.key_expr) for reply in replies if reply.ok is not None}

    wait_for(
        lambda: kept() == {"dbml/own/n4/r1/camera/dbm/priority"},
        timeout_s=10,
        what="the optimizer's reply",
    )


@pytest.mark.integration
def test_graph_tokens_carry_the_certificate_s_name(
    mesh: tuple[Path, dict[str, zenoh.Session]],
) -> None:
    _, sessions = mesh
    tokens: list[str] = []
    lock = threading.Lock()

    def on_token(sample: zenoh.Sample) -> None:
        with lock:
            tokens.append(str(sample.key_expr))

    watcher = sessions["opt"].liveliness().declare_subscriber("dbml/**", on_token, history=True)
    forbidden = [
        sessions["r1"].liveliness().declare_token("dbml/graph/pub/r2/x.1/optimized/r2/camera"),
        sessions["op"].liveliness().declare_token("dbml/graph/sub/r1/y.1/optimized/r1/camera"),
        sessions["r1"].liveliness().declare_token("dbml/elsewhere/x"),
    ]
    allowed = [
        sessions["r1"].liveliness().declare_token("dbml/node/abc/def"),
        sessions["op"].liveliness().declare_token("dbml/graph/sub/op/y.2/optimized/r1/camera"),
        sessions["r1"].liveliness().declare_token("dbml/graph/pub/r1/x.2/optimized/r1/camera"),
    ]
    expected = {
        "dbml/node/abc/def",
        "dbml/graph/sub/op/y.2/optimized/r1/camera",
        "dbml/graph/pub/r1/x.2/optimized/r1/camera",
    }

    def seen() -> set[str]:
        with lock:
            return set(tokens)

    wait_for(lambda: expected <= seen(), timeout_s=10, what="the allowed tokens")
    late = {str(r.ok.key_expr) for r in sessions["opt"].liveliness().get("dbml/**") if r.ok}
    assert seen() == expected
    assert late == expected
    del watcher, forbidden, allowed


@pytest.mark.integration
def test_processes_of_one_node_meet_directly(mesh: tuple[Path, dict[str, zenoh.Session]]) -> None:
    """A second and third operator process find the endpoint taken, and still meet each other.

    Each listens on a port of its own, learnt by the others by gossip: no process depends on
    another to forward (which would make the forwarder the subject of the access control).
    """
    directory, sessions = mesh
    second = open_node(directory / "op.json5")
    third = open_node(directory / "op.json5")
    try:
        zids = {name: str(session.info.zid()) for name, session in sessions.items()}
        zids |= {"second": str(second.info.zid()), "third": str(third.info.zid())}

        def meets_everyone(session: zenoh.Session, me: str) -> bool:
            peers = {str(zid) for zid in session.info.peers_zid()}
            return peers == {zid for name, zid in zids.items() if name != me}

        wait_for(
            lambda: meets_everyone(second, "second") and meets_everyone(third, "third"),
            timeout_s=15,
            what="the operator's processes to meet every process",
        )
        at_second = Recorder(second)
        listening(at_second, third, "dbml/param/dbm/strategy")
    finally:
        second.close()  # type: ignore[no-untyped-call]
        third.close()  # type: ignore[no-untyped-call]


def rogue_config(endpoint: str, tls: dict[str, object]) -> zenoh.Config:
    """A session that must connect to ``endpoint`` within 1 s or fail to open."""
    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("transport/shared_memory/enabled", "false")
    config.insert_json5("listen/endpoints", "[]")
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    config.insert_json5("connect/timeout_ms", "1000")
    config.insert_json5("connect/exit_on_failure", "true")
    for field, value in tls.items():
        config.insert_json5(f"transport/link/tls/{field}", json.dumps(value))
    return config


def open_each(endpoints: list[str], tls: dict[str, object]) -> list[zenoh.Session | None]:
    """One session per endpoint, opened at once; None where zenoh refused to open it.

    One endpoint each: with several, a peer's open fails when any one of them does not connect
    in time, so a failure would not say that none accepted.
    """

    def attempt(endpoint: str) -> zenoh.Session | None:
        try:
            return zenoh.open(rogue_config(endpoint, tls))
        except zenoh.ZError:
            return None

    with ThreadPoolExecutor(len(endpoints)) as pool:
        return list(pool.map(attempt, endpoints))


@pytest.mark.integration
@pytest.mark.parametrize("credentials", ["plain tcp", "no certificate", "another CA's r1"])
def test_a_session_without_a_fleet_certificate_reaches_no_node(
    mesh: tuple[Path, dict[str, zenoh.Session]], tmp_path: Path, credentials: str
) -> None:
    directory, sessions = mesh
    endpoints = [
        json.loads(
            zenoh.Config.from_file(str(directory / f"{n}.json5")).get_json("listen/endpoints")
        )[0]
        for n in NODES
    ]
    init_fleet(tmp_path / "rogue", small_fleet())
    ca = str(directory / CA_CERTIFICATE)
    tls: dict[str, object] = {"root_ca_certificate": ca}
    if credentials == "plain tcp":
        tls = {}
    elif credentials == "another CA's r1":
        tls |= {
            "connect_certificate": str(tmp_path / "rogue" / "r1.pem"),
            "connect_private_key": str(tmp_path / "rogue" / "r1.key"),
            "enable_mtls": True,
        }
    tried = (
        [e.replace("tls/", "tcp/") for e in endpoints] if credentials == "plain tcp" else endpoints
    )
    assert open_each(tried, tls) == [None] * len(NODES)
    assert all(len(list(s.info.peers_zid())) == 3 for s in sessions.values())
    # the control: the same session with the operator's certificate gets into every node
    tls = {
        "root_ca_certificate": ca,
        "connect_certificate": str(directory / "op.pem"),
        "connect_private_key": str(directory / "op.key"),
        "enable_mtls": True,
    }
    opened = open_each(endpoints, tls)
    for session in opened:
        if session is not None:
            session.close()  # type: ignore[no-untyped-call]
    assert None not in opened
