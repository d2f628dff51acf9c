"""A ROS 2 node over a phalanx Zenoh session, as rmw_zenoh makes one: the node's, each
publisher's and each subscription's liveliness token (what `ros2 node list` and `ros2
topic list` read), publishers that put CDR payloads on rmw_zenoh's data keys with its
attachment, and subscriptions on those keys.

The attachment of every sample (rmw_zenoh's design.md, "Publishers"): the publisher's
sequence number (int64, from 1), the source timestamp (int64 ns since the Unix epoch)
and the publisher's GID (16 bytes, a length byte first), in Zenoh's own serialisation,
which is what rmw_zenoh's `AttachmentData` uses: each int64 little-endian, the bytes
after their LEB128 length, packed here with `struct` (the tests hold it to
`zenoh.ext.z_serialize`'s bytes). rmw_zenoh makes a GID by hashing the entity's token
with XXH3; ours hashes it with BLAKE2b: a receiver only compares GIDs, so any 16 bytes
unique to the publisher do.

A transient-local publisher (`/tf_static`) is a Zenoh advanced publisher with a cache of
its depth, publisher detection and sample-miss detection (a reliable one), as
rmw_zenoh declares one, so a late subscriber's query gets the last message.
"""

from __future__ import annotations

import hashlib
import struct
import threading
import time
from collections import deque
from typing import Any

from phalanx.ros2.names import SUBSCRIPTION, NodeId, node_token, publisher_token
from phalanx.ros2.topics import RosTopic
from phalanx.wire.transport import FleetSession

# rmw_zenoh's heartbeat period of a reliable transient-local publisher (s), by which
# subscribers notice a message they missed and fetch it from the cache.
HEARTBEAT_S = 0.5
_SEQUENCE_AND_STAMP = struct.Struct("<qq")
GID_BYTES = 16
_GID_LENGTH = bytes((GID_BYTES,))  # LEB128: one byte under 128


def gid_of(token: str) -> bytes:
    """A publisher's 16-byte GID, from its liveliness token."""
    return hashlib.blake2b(token.encode("utf-8"), digest_size=GID_BYTES).digest()


def attachment(sequence: int, source_ns: int, gid: bytes) -> bytes:
    """rmw_zenoh's attachment of a sample (33 bytes with a 16-byte GID)."""
    if len(gid) != GID_BYTES:
        raise ValueError(f"a GID has {GID_BYTES} bytes, not {len(gid)}")
    return _SEQUENCE_AND_STAMP.pack(sequence, source_ns) + _GID_LENGTH + gid


class RosPublisher:
    """One topic's publisher: its token held, `put` sends a CDR payload (thread-safe)."""

    def __init__(self, fleet: FleetSession, node: NodeId, entity_id: int, topic: RosTopic) -> None:
        self.topic = topic
        self.key = topic.key(node.domain_id)
        self.token = publisher_token(
            node, entity_id, topic=topic.name, ros_type=topic.ros_type,
            type_hash=topic.type_hash, qos=topic.qos,
        )  # fmt: skip
        self.gid = gid_of(self.token)
        self.sent = 0
        self._lock = threading.Lock()
        self._publisher = fleet.hold(_declare(fleet.zenoh, self.key, topic))
        fleet.hold(fleet.zenoh.liveliness().declare_token(self.token))

    def put(self, payload: bytes | bytearray) -> None:
        """Send `payload` (CDR) with the attachment of the next sequence number."""
        with self._lock:
            self.sent += 1
            extra = attachment(self.sent, time.time_ns(), self.gid)
            self._publisher.put(payload, attachment=extra)


class RosSubscription:
    """One topic's subscription: its token held; Zenoh's thread only keeps each sample's
    CDR payload, in a ring of the topic's depth (the oldest dropped, counted), until
    `take` (the attachment is not needed: the newest sample is what counts).
    """

    def __init__(self, fleet: FleetSession, node: NodeId, entity_id: int, topic: RosTopic) -> None:
        self.topic = topic
        self.key = topic.key(node.domain_id)
        self.token = publisher_token(
            node, entity_id, topic=topic.name, ros_type=topic.ros_type,
            type_hash=topic.type_hash, qos=topic.qos, kind=SUBSCRIPTION,
        )  # fmt: skip
        self.dropped = 0
        self._ring: deque[bytes] = deque(maxlen=topic.qos.depth)
        self._lock = threading.Lock()
        fleet.hold(fleet.zenoh.declare_subscriber(self.key, self._put))
        fleet.hold(fleet.zenoh.liveliness().declare_token(self.token))

    def _put(self, sample: Any) -> None:
        payload = sample.payload.to_bytes()
        with self._lock:
            if len(self._ring) == self._ring.maxlen:
                self.dropped += 1
            self._ring.append(payload)

    def take(self) -> list[bytes]:
        """The payloads that arrived since the last call, oldest first."""
        with self._lock:
            taken = list(self._ring)
            self._ring.clear()
        return taken


def _declare(session: Any, key: str, topic: RosTopic) -> Any:
    import zenoh
    from zenoh.ext import CacheConfig, MissDetectionConfig, declare_advanced_publisher

    if topic.qos.transient_local:  # reliable too: with rmw_zenoh's sporadic heartbeat
        return declare_advanced_publisher(
            session,
            key,
            cache=CacheConfig(max_samples=topic.qos.depth),
            sample_miss_detection=MissDetectionConfig(
                heartbeat=None, sporadic_heartbeat=HEARTBEAT_S
            ),
            publisher_detection=True,
        )
    return session.declare_publisher(
        key, congestion_control=zenoh.CongestionControl.DROP, reliability=zenoh.Reliability.RELIABLE
    )


class RosNode:
    """A node in the ROS graph on `fleet`'s Zenoh session: its token is held until the
    session closes, and so are its publishers' (node id 0; entities numbered from 1).
    """

    def __init__(self, fleet: FleetSession, *, domain_id: int, namespace: str, name: str) -> None:
        zid = str(fleet.zenoh.info.zid())
        self.node = NodeId(domain_id, zid, 0, namespace, name)
        self.token = node_token(self.node)
        self._fleet = fleet
        self._entities = 0
        fleet.hold(fleet.zenoh.liveliness().declare_token(self.token))

    def publisher(self, topic: RosTopic) -> RosPublisher:
        """Declare a publisher of `topic` (and its token)."""
        self._entities += 1
        return RosPublisher(self._fleet, self.node, self._entities, topic)

    def subscription(self, topic: RosTopic) -> RosSubscription:
        """Declare a subscription to `topic` (and its token)."""
        self._entities += 1
        return RosSubscription(self._fleet, self.node, self._entities, topic)
