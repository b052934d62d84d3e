"""Typed messages of the TwinFocus node graph and their msgpack codec.

Each topic kind has one message type (``TOPIC_TYPES``); every message starts with a
:class:`Header` (stamp_ns, seq, frame_id). ``encode_frames``/``decode_frames`` are the bus form
(arrays as separate zero-copy frames), ``encode``/``decode`` the one-blob form of MCAP logs.
"""

from msgs.codec import decode, decode_frames, encode, encode_frames
from msgs.messages import (
    TOPIC_TYPES,
    AutofocusResult,
    Image,
    NodeStatus,
    Pose,
    RadarFrame,
    SarMeasurement,
    StereoFrame,
    TwinTemplate,
)
from msgs.schema import MESSAGE_TYPES, BusMessage, Header, MessageError, now_ns, schema_of

__all__ = [
    "TOPIC_TYPES",
    "MESSAGE_TYPES",
    "BusMessage",
    "Header",
    "MessageError",
    "now_ns",
    "schema_of",
    "encode",
    "decode",
    "encode_frames",
    "decode_frames",
    "RadarFrame",
    "Pose",
    "StereoFrame",
    "SarMeasurement",
    "TwinTemplate",
    "AutofocusResult",
    "Image",
    "NodeStatus",
]
