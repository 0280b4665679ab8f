"""rmw_zenoh's naming on the Zenoh bus: data key expressions, liveliness tokens and sample attachments.

Follows ``docs/design.md`` of ros2/rmw_zenoh (sections "Topic and Service name mapping to Zenoh
key expressions", "Graph Cache" and "Publishers"):

- data: ``<domain_id>/<fully qualified name without leading slash>/<dds type name>/<type hash>``
- node token: ``@ros2_lv/<domain_id>/<session_id>/<node_id>/<node_id>/NN/<enclave>/<namespace>/<node_name>``
- endpoint token: ``@ros2_lv/<domain_id>/<session_id>/<node_id>/<entity_id>/<MP|MS>/<enclave>/<namespace>/
  <node_name>/<qualified topic>/<dds type name>/<type hash>/<qos>``, with every ``/`` of the enclave,
  namespace and topic replaced by ``%`` (an empty enclave or namespace becomes ``%``)
- attachment of every sample: int64 sequence number, int64 source timestamp (ns since the epoch),
  both little-endian, then the 16-byte publisher GID prefixed by its length as one byte.
"""

from __future__ import annotations

import hashlib
import re
import struct
from typing import Literal

from pydantic import BaseModel, Field

from twohr.messages import MessageError

from . import msgs

ADMIN_SPACE = "@ros2_lv"
#: rmw_zenoh's compact QoS for RELIABLE, VOLATILE, KEEP_LAST 10: the fields equal to its defaults are left empty
DEFAULT_QOS = "::,10:,:,:,,"
GID_SIZE = 16
_ATTACHMENT = struct.Struct("<qqB")
_NAME = re.compile(r"^(/[A-Za-z_][A-Za-z0-9_]*)*/?$")


def qualified_name(namespace: str, name: str) -> str:
    """The fully qualified ROS name of ``name`` in ``namespace`` (``/robot1`` + ``pose`` -> ``/robot1/pose``);
    a name that starts with ``/`` is already absolute."""
    if name.startswith("/"):
        full = name
    else:
        full = "/" + "/".join(part for part in (namespace.strip("/"), name) if part)
    if not _NAME.match(full) or full == "/":
        raise ValueError(f"invalid ROS name {full!r}: use letters, digits and '_' between slashes")
    return full.rstrip("/")


def topic_key(domain_id: int, topic: str, message: type) -> str:
    """The Zenoh key a ROS 2 node on rmw_zenoh publishes ``topic`` (fully qualified) of this type on."""
    return f"{domain_id}/{topic.strip('/')}/{msgs.dds_type(message)}/{msgs.type_hash(message)}"


def topic_key_any_hash(domain_id: int, topic: str, message: type) -> str:
    """The key expression for a topic whatever the publisher's type hash (Humble sends ``TypeHashNotSupported``)."""
    return f"{domain_id}/{topic.strip('/')}/{msgs.dds_type(message)}/*"


def mangle(name: str) -> str:
    """A name as one key chunk: every ``/`` becomes ``%``; empty stays ``%``."""
    return name.replace("/", "%") or "%"


class NodeInfo(BaseModel):
    """The identity of one ROS 2 node on the bus."""

    domain_id: int = Field(0, ge=0)
    session_id: str = Field(min_length=1, description="the Zenoh session id, as hex")
    node_id: int = Field(0, ge=0)
    namespace: str = "/"
    name: str = Field(min_length=1)
    enclave: str = ""

    def _prefix(self, entity_id: int, kind: str) -> str:
        return (f"{ADMIN_SPACE}/{self.domain_id}/{self.session_id}/{self.node_id}/{entity_id}/{kind}/"
                f"{mangle(self.enclave)}/{mangle(self.namespace.rstrip('/'))}/{self.name}")

    def node_token(self) -> str:
        """The liveliness token that announces the node (kind ``NN``)."""
        return self._prefix(self.node_id, "NN")

    def endpoint_token(self, entity_id: int, kind: Literal["MP", "MS"], topic: str, message: type,
                       qos: str = DEFAULT_QOS) -> str:
        """The liveliness token of a publisher (``MP``) or subscription (``MS``) on a fully qualified topic."""
        return (f"{self._prefix(entity_id, kind)}/{mangle(topic)}/{msgs.dds_type(message)}/"
                f"{msgs.type_hash(message)}/{qos}")


def make_gid(token: str) -> bytes:
    """A stable 16-byte GID for an entity, derived from its liveliness token (as rmw_zenoh derives its own)."""
    return hashlib.blake2b(token.encode(), digest_size=GID_SIZE).digest()


class Attachment(BaseModel):
    """What rmw_zenoh attaches to every published sample."""

    sequence_number: int
    source_timestamp_ns: int
    source_gid: bytes = Field(min_length=GID_SIZE, max_length=GID_SIZE)

    def encode(self) -> bytes:
        return _ATTACHMENT.pack(self.sequence_number, self.source_timestamp_ns, GID_SIZE) + self.source_gid

    @classmethod
    def decode(cls, data: bytes) -> Attachment:
        if len(data) != _ATTACHMENT.size + GID_SIZE:
            raise MessageError(f"rmw_zenoh attachment of {len(data)} bytes, expected {_ATTACHMENT.size + GID_SIZE}")
        sequence, stamp, gid_size = _ATTACHMENT.unpack_from(data)
        if gid_size != GID_SIZE:
            raise MessageError(f"rmw_zenoh attachment GID length {gid_size}, expected {GID_SIZE}")
        return cls(sequence_number=sequence, source_timestamp_ns=stamp, source_gid=data[_ATTACHMENT.size:])
