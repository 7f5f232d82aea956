"""Fast DDS, the default ROS 2 middleware, tuned for a graph that follows processes quickly.

dbml's rclpy transport learns who listens from the ROS 2 graph. With Fast DDS's defaults a new
subscriber in another process may take seconds to appear, and a SIGKILLed one stays for its
participant's 20-s lease. A default participant profile with a short lease and frequent
announcements (:func:`discovery_profile_xml`, installed by :func:`apply_discovery_profile`)
cuts the first's worst case to about 1 s and the second to about 3 s; transports stay as the
RMW sets them (UDPv4 and shared memory).

Measured 2026-11-24 (Kilted wheels, Fast DDS 3.2, one shared 2-core host with other ROS 2 runs
going on; min / median / max in s, 10 runs each): a publisher process polls
``get_subscription_count()`` every ms; a subscriber process in its domain (private context,
``SignalHandlerOptions.NO``) creates its subscription, and is SIGKILLed once seen. Both are
``python -c`` children with :func:`dbml.harness.ros2env.ros2_child_env`'s environment, with
and without ``FASTDDS_DEFAULT_PROFILES_FILE``::

                                        Fast DDS defaults      this profile
    subscriber seen, from its creation  0.00 / 0.00 / 2.40     0.00 / 0.04 / 0.92
    SIGKILLed subscriber gone           19.98 / 19.99 / 20.00  2.98 / 2.99 / 3.00

A new publisher process seeing a running subscriber (15 runs): median 0.07-0.09, max 2.48 by
default; median 0.13-0.15, max 1.27 with the profile. Discovery is usually quick either way;
the profile bounds its tail by the 1-s announcement period instead of 3 s, and a killed process
leaves the graph after the 3-s lease instead of 20 s.

:func:`gid_host_id` reads the host part of a Fast DDS GID, the only hint of where a remote
endpoint runs that the ROS 2 graph gives.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Mapping, MutableMapping, Sequence
from pathlib import Path

__all__ = [
    "CWD_PROFILES_FILE",
    "DEFAULT_PROFILES_FILE",
    "FASTDDS_RMWS",
    "GID_BYTES",
    "LEGACY_PROFILES_FILE",
    "PROFILE_FILE_NAME",
    "PROFILE_NAME",
    "apply_discovery_profile",
    "discovery_profile_xml",
    "gid_host_id",
    "is_fastdds",
]

DEFAULT_PROFILES_FILE = "FASTDDS_DEFAULT_PROFILES_FILE"
"""The variable Fast DDS 3 reads its XML profiles from (2.x read ``FASTRTPS_...``)."""
LEGACY_PROFILES_FILE = "FASTRTPS_DEFAULT_PROFILES_FILE"
"""Fast DDS 2's name; rmw_fastrtps 9 still loads it (with a deprecation warning)."""
CWD_PROFILES_FILE = "DEFAULT_FASTDDS_PROFILES.xml"
"""Fast DDS also loads this file from the working directory unless ``SKIP_DEFAULT_XML_FILE=1``."""
FASTDDS_RMWS = frozenset({"rmw_fastrtps_cpp", "rmw_fastrtps_dynamic_cpp"})
"""``RMW_IMPLEMENTATION`` values that mean Fast DDS (unset means it too: the default RMW)."""
PROFILE_NAME = "dbml_discovery"
"""The participant profile's name: distinct, so it never clashes with a user's profile."""
PROFILE_FILE_NAME = "dbml-fastdds-discovery.xml"
"""What :func:`apply_discovery_profile` writes into its directory."""

GID_BYTES = 16
"""An endpoint GID's size in rclpy's graph and message info (rmw's ``RMW_GID_STORAGE_SIZE``)."""

_EPROSIMA_VENDOR = b"\x01\x0f"
_NS_PER_S = 1_000_000_000


def _duration(seconds: float) -> str:
    """``seconds`` as Fast DDS's ``durationType`` (``sec`` and ``nanosec``, both integers)."""
    total_ns = round(seconds * _NS_PER_S)
    sec, nanosec = divmod(total_ns, _NS_PER_S)
    return f"<sec>{sec}</sec><nanosec>{nanosec}</nanosec>"


def discovery_profile_xml(
    *,
    lease_s: float = 3.0,
    announce_period_s: float = 1.0,
    initial_announcements: int = 10,
    initial_period_s: float = 0.1,
) -> str:
    """A Fast DDS XML file whose default participant profile discovers and forgets quickly.

    ``lease_s``: how long peers keep a silent participant (Fast DDS: 20 s), so a killed process
    leaves their graph after about that. ``announce_period_s``: the period of the participant's
    announcements after the initial ones (Fast DDS: 3 s); it must be below ``lease_s``.
    ``initial_announcements`` at ``initial_period_s`` (Fast DDS: 5 at 0.1 s) cover a peer that
    starts a moment later. Everything else (transports, ports, QoS) keeps the RMW's values.
    Elements as in Fast DDS 3.2's ``fastdds_profiles.xsd`` (``discoverySettingsType``).
    """
    if not 0 < announce_period_s < lease_s:
        raise ValueError(
            f"announce_period_s={announce_period_s} must be above 0 and below lease_s={lease_s}"
        )
    if initial_announcements < 0 or initial_period_s <= 0:
        raise ValueError(
            f"initial_announcements={initial_announcements} must be >= 0 and "
            f"initial_period_s={initial_period_s} above 0"
        )
    return f"""\
<?xml version="1.0" encoding="UTF-8" ?>
<!-- dbml: a short lease and frequent announcements, so the ROS 2 graph follows processes. -->
<dds xmlns="http://www.eprosima.com">
  <profiles>
    <participant profile_name="{PROFILE_NAME}" is_default_profile="true">
      <rtps>
        <builtin>
          <discovery_config>
            <leaseDuration>{_duration(lease_s)}</leaseDuration>
            <leaseAnnouncement>{_duration(announce_period_s)}</leaseAnnouncement>
            <initialAnnouncements>
              <count>{initial_announcements}</count>
              <period>{_duration(initial_period_s)}</period>
            </initialAnnouncements>
          </discovery_config>
        </builtin>
      </rtps>
    </participant>
  </profiles>
</dds>
"""


def is_fastdds(environ: Mapping[str, str] | None = None) -> bool:
    """Whether ROS 2 in an environment ``environ`` (default: this one) runs on Fast DDS."""
    env = os.environ if environ is None else environ
    return env.get("RMW_IMPLEMENTATION", "").strip() in FASTDDS_RMWS | {""}


def _own_profiles(environ: Mapping[str, str]) -> bool:
    """Whether the user gave Fast DDS profiles of their own (a variable or the cwd's file)."""
    if environ.get(DEFAULT_PROFILES_FILE) or environ.get(LEGACY_PROFILES_FILE):
        return True
    skip = environ.get("SKIP_DEFAULT_XML_FILE", "").startswith("1")
    return not skip and (Path.cwd() / CWD_PROFILES_FILE).is_file()


def apply_discovery_profile(
    directory: Path, environ: MutableMapping[str, str] = os.environ
) -> Path | None:
    """Write the discovery profile into ``directory`` and point ``environ`` at it; its path.

    Only for Fast DDS (``RMW_IMPLEMENTATION`` unset or a Fast DDS RMW) and only when the user has
    no profile of their own (``FASTDDS_DEFAULT_PROFILES_FILE``, the older
    ``FASTRTPS_DEFAULT_PROFILES_FILE``, or a ``DEFAULT_FASTDDS_PROFILES.xml`` in the working
    directory): else None, and nothing changes. Fast DDS reads the variable once, at the first
    participant of the process: call this before the first ``rclpy.init`` (or on a child's
    environment). ``RMW_FASTRTPS_USE_QOS_FROM_XML`` is left alone: it concerns publishers' and
    subscriptions' QoS, and the participant profile applies without it.
    """
    if not is_fastdds(environ) or _own_profiles(environ):
        return None
    directory.mkdir(parents=True, exist_ok=True)
    path = (directory / PROFILE_FILE_NAME).resolve()
    with tempfile.NamedTemporaryFile(
        "w", encoding="utf-8", dir=path.parent, prefix=f".{path.name}.", delete=False
    ) as partial:
        partial.write(discovery_profile_xml())
    os.chmod(partial.name, 0o644)  # nothing secret; a child under another user reads it too
    Path(partial.name).replace(path)  # atomic: a process starting now reads all of it or none
    environ[DEFAULT_PROFILES_FILE] = str(path)
    return path


def gid_host_id(gid: bytes | Sequence[int]) -> int | None:
    """The host id in a Fast DDS endpoint GID (rclpy's ``TopicEndpointInfo.endpoint_gid``).

    Fast DDS lays a GID out as vendor ``01 0f``, host id (2 bytes, little-endian), PID (2),
    random (2), participant (4), entity (4). Equal host ids mean, most likely, one host: the id
    is a 16-bit hash of the process's non-loopback IPv4 addresses (so it follows network
    namespaces and containers, two hosts may collide, and every process without such an address
    gets ``0x017f``). None for another vendor's GID or one that is not 16 bytes.
    """
    try:
        raw = bytes(gid)
    except (TypeError, ValueError):
        return None
    if len(raw) != GID_BYTES or raw[:2] != _EPROSIMA_VENDOR:
        return None
    return int.from_bytes(raw[2:4], "little")
