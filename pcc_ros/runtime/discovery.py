"""ROS 2 discovery settings -> a Cyclone DDS configuration, as rmw_cyclonedds derives it.

Environment followed (Jazzy semantics):

* ``ROS_DOMAIN_ID`` (default 0).
* ``ROS_AUTOMATIC_DISCOVERY_RANGE``: ``LOCALHOST`` -> the loopback interface, no multicast,
  automatic participant index and the peer 127.0.0.1 (what rmw_cyclonedds configures; without
  it a ROS node in localhost mode and this runtime never see each other); ``OFF`` -> loopback
  without peers; ``SUBNET`` (default) / ``SYSTEM_DEFAULT`` -> Cyclone's defaults.
  The deprecated ``ROS_LOCALHOST_ONLY=1`` means ``LOCALHOST``.
* ``ROS_STATIC_PEERS`` (``;``-separated hosts) are added as unicast peers.
* ``CYCLONEDDS_URI``: when set, the user's configuration is used unchanged.

Large best-effort samples (a 1.9 MB scan is ~1400 fragments at Cyclone's default 1344 B
fragment size) are lost over loopback when the socket receive buffer overflows, so every
configuration asks for a large receive buffer (``SocketReceiveBufferSize max``; the kernel
caps it at ``net.core.rmem_max`` — raise that, see docs/dds.md) and, on loopback, for
64 kB messages and fragments (MTU 65536), which cuts the packet count ~45x.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from xml.sax.saxutils import quoteattr

from pcc_ros.errors import ConfigError

RANGES = ("SUBNET", "LOCALHOST", "OFF", "SYSTEM_DEFAULT")
#: Requested socket receive buffer (bytes); the kernel grants at most net.core.rmem_max.
RECEIVE_BUFFER_BYTES = 16 * 1024 * 1024
#: On loopback: one UDP datagram per 64 kB instead of per 1344 B.
LOOPBACK_MESSAGE_BYTES = 65000


@dataclass(frozen=True)
class Discovery:
    domain_id: int = 0
    range: str = "SUBNET"
    static_peers: tuple[str, ...] = ()
    user_uri: str | None = None

    @classmethod
    def from_env(cls, env: Mapping[str, str] | None = None) -> Discovery:
        env = os.environ if env is None else env
        raw_id = env.get("ROS_DOMAIN_ID", "").strip() or "0"
        try:
            domain_id = int(raw_id)
        except ValueError:
            raise ConfigError(f"ROS_DOMAIN_ID={raw_id!r} is not an integer") from None
        if not 0 <= domain_id <= 232:
            raise ConfigError(f"ROS_DOMAIN_ID={domain_id} is outside 0..232")
        rng = env.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "").strip().upper()
        if not rng:
            rng = "LOCALHOST" if env.get("ROS_LOCALHOST_ONLY", "").strip() == "1" else "SUBNET"
        if rng not in RANGES:
            raise ConfigError(f"ROS_AUTOMATIC_DISCOVERY_RANGE={rng!r} is not one of {', '.join(RANGES)}")
        peers = tuple(p.strip() for p in env.get("ROS_STATIC_PEERS", "").split(";") if p.strip())
        return cls(domain_id, rng, peers, env.get("CYCLONEDDS_URI") or None)

    def cyclone_xml(self) -> str | None:
        """The configuration to create the domain with (``None``: the user's ``CYCLONEDDS_URI``)."""
        if self.user_uri:
            return None
        general, discovery = [], []
        loopback = self.range in ("LOCALHOST", "OFF")
        if loopback:
            general += [
                '<Interfaces><NetworkInterface address="127.0.0.1"/></Interfaces>',
                "<AllowMulticast>false</AllowMulticast>",
                f"<MaxMessageSize>{LOOPBACK_MESSAGE_BYTES}B</MaxMessageSize>",
                f"<FragmentSize>{LOOPBACK_MESSAGE_BYTES - 1000}B</FragmentSize>",
            ]
            discovery += [
                "<ParticipantIndex>auto</ParticipantIndex>",
                "<MaxAutoParticipantIndex>32</MaxAutoParticipantIndex>",
            ]
        peers = list(self.static_peers)
        if self.range == "LOCALHOST":
            peers.insert(0, "127.0.0.1")
        if peers:
            discovery.append("<Peers>" + "".join(f"<Peer address={quoteattr(p)}/>" for p in peers) + "</Peers>")
        parts = ['<CycloneDDS><Domain Id="any">']
        if general:
            parts.append("<General>" + "".join(general) + "</General>")
        if discovery:
            parts.append("<Discovery>" + "".join(discovery) + "</Discovery>")
        parts.append(f'<Internal><SocketReceiveBufferSize min="default" max="{RECEIVE_BUFFER_BYTES}B"/></Internal>')
        parts.append("</Domain></CycloneDDS>")
        return "".join(parts)


def rmem_max() -> int | None:
    """``net.core.rmem_max`` of this Linux host (None elsewhere)."""
    try:
        return int(open("/proc/sys/net/core/rmem_max").read())
    except (OSError, ValueError):
        return None
