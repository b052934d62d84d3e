"""msgpack codec for typed messages, numpy arrays carried as dtype + shape + raw buffer.

Two forms of the same envelope ``{"type": "RadarFrame", "v": 1, "fields": {...}}``:

* **frames** (the bus): ``[envelope, buffer_0, buffer_1, ...]``. Each array field is
  ``{"__ndarray__": i, "dtype": "<c8", "shape": [K, N]}`` in the envelope and its bytes travel
  as frame ``1 + i``, so ZeroMQ sends the array's memory without a copy (the sender must not
  change an array after publishing it) and the receiver wraps the received frame with
  ``np.frombuffer`` (no copy; the array is read-only).
* **bytes** (MCAP logs, message encoding ``msgpack``): one self-describing msgpack map where
  each array is ``{"__ndarray__": -1, "dtype": ..., "shape": ..., "data": <bin>}``, readable
  by any msgpack library.

Nothing is pickled: dtypes must be exactly the schema's (a string compare, never
``np.dtype(untrusted)``), and decoding validates every field against the message schema, raising
:class:`~msgs.schema.MessageError` with the type, field and problem.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import msgpack
import numpy as np

from msgs.schema import MESSAGE_TYPES, BusMessage, Header, MessageError, field_specs, validate

FORMAT_VERSION = 1
_ND = "__ndarray__"


def _raw(a: np.ndarray) -> memoryview:
    """The array's bytes as a flat byte view (no copy for a C-contiguous array)."""
    a = np.ascontiguousarray(a)
    return a.reshape(-1).view(np.uint8).data


def _envelope(msg: Any, buffers: list | None, publisher: str) -> dict:
    cls = type(msg)
    if getattr(cls, "TYPE", None) not in MESSAGE_TYPES:
        raise MessageError(f"cannot encode {cls.__name__}: not a registered message type")
    validate(msg, strict=False)
    fields: dict[str, Any] = {"header": msg.header.to_wire()}
    for name, spec in field_specs(cls):
        value = getattr(msg, name)
        if spec.kind == "array":
            if value is None:
                fields[name] = None
                continue
            a = np.ascontiguousarray(value)
            desc = {_ND: -1, "dtype": a.dtype.str, "shape": list(a.shape)}
            if buffers is None:
                desc["data"] = _raw(a)
            else:
                desc[_ND] = len(buffers)
                buffers.append(_raw(a))
            fields[name] = desc
        else:
            fields[name] = value
    env = {"type": cls.TYPE, "v": FORMAT_VERSION, "fields": fields}
    if publisher:
        env["publisher"] = publisher
    return env


def encode_frames(msg: Any, publisher: str = "") -> list:
    """Encode for the bus: ``[envelope bytes, array buffer, ...]`` (buffers are zero-copy views)."""
    buffers: list = []
    env = _envelope(msg, buffers, publisher)
    return [msgpack.packb(env, use_bin_type=True), *buffers]


def encode(msg: Any) -> bytes:
    """Encode as one self-describing msgpack blob (MCAP message data)."""
    return msgpack.packb(_envelope(msg, None, ""), use_bin_type=True)


def _as_buffer(frame: Any) -> memoryview:
    buf = getattr(frame, "buffer", None)  # zmq.Frame received with copy=False
    return buf if buf is not None else memoryview(frame)


def _unpack(blob: Any, where: str) -> dict:
    try:
        env = msgpack.unpackb(blob, raw=False, strict_map_key=True)
    except Exception as exc:  # msgpack raises several unrelated types for corrupt input
        raise MessageError(f"{where}: not a msgpack message ({type(exc).__name__}: {exc})") from None
    if not isinstance(env, dict) or "type" not in env or "fields" not in env:
        raise MessageError(f"{where}: not a TwinFocus message envelope (need 'type' and 'fields')")
    if env.get("v") != FORMAT_VERSION:
        raise MessageError(
            f"{where}: unsupported message format version {env.get('v')!r} (this build reads {FORMAT_VERSION})"
        )
    return env


def _array(desc: Any, spec, where: str, name: str, buffers: Sequence | None) -> np.ndarray | None:
    if desc is None:
        return None  # validate() decides whether None is allowed
    if not isinstance(desc, dict) or _ND not in desc or "dtype" not in desc or "shape" not in desc:
        raise MessageError(f"{where}: field '{name}' must be an encoded array (dict with {_ND}, dtype, shape)")
    want = spec.dtype.str
    if desc["dtype"] != want:
        raise MessageError(f"{where}: field '{name}' must have dtype {spec.dtype.name} ({want}), got {desc['dtype']!r}")
    shape = desc["shape"]
    if not isinstance(shape, list) or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shape):
        raise MessageError(f"{where}: field '{name}' has a bad shape {shape!r}")
    count = 1
    for s in shape:
        count *= s
    if buffers is None:
        data = desc.get("data")
        if not isinstance(data, (bytes, bytearray)):
            raise MessageError(f"{where}: field '{name}' has no inline 'data' bytes")
        buf = memoryview(data)
    else:
        i = desc[_ND]
        if not isinstance(i, int) or isinstance(i, bool) or not 0 <= i < len(buffers):
            raise MessageError(f"{where}: field '{name}' refers to buffer {i!r}, the message has {len(buffers)}")
        buf = _as_buffer(buffers[i])
    nbytes = count * spec.dtype.itemsize
    if buf.nbytes != nbytes:
        raise MessageError(
            f"{where}: field '{name}' has {buf.nbytes} bytes of data, shape {tuple(shape)} of {spec.dtype.name} needs {nbytes}"
        )
    return np.frombuffer(buf, dtype=spec.dtype, count=count).reshape(shape)


def _build(env: dict, buffers: Sequence | None, where: str, expect: type[BusMessage] | None) -> Any:
    type_name = env["type"]
    cls = MESSAGE_TYPES.get(type_name) if isinstance(type_name, str) else None
    if cls is None:
        raise MessageError(f"{where}: unknown message type {type_name!r} (known: {', '.join(sorted(MESSAGE_TYPES))})")
    if expect is not None and cls is not expect:
        raise MessageError(f"{where}: expected a {expect.TYPE} message, got {cls.TYPE}")
    where = f"{where}: {cls.TYPE}"
    fields = env["fields"]
    if not isinstance(fields, dict):
        raise MessageError(f"{where}: 'fields' must be a map")
    specs = dict(field_specs(cls))
    unknown = sorted(set(fields) - set(specs) - {"header"})
    if unknown:
        raise MessageError(f"{where}: unknown field(s) {', '.join(map(repr, unknown))}")
    if "header" not in fields:
        raise MessageError(f"{where}: field 'header' is missing")
    values: dict[str, Any] = {"header": Header.from_wire(fields["header"], where)}
    for f in dataclasses.fields(cls):
        if f.name == "header":
            continue
        spec = specs[f.name]
        if f.name not in fields:
            if spec.kind == "array" and spec.optional:
                values[f.name] = None
                continue
            # A field added to the schema after the message was written: take its default.
            if f.default is not dataclasses.MISSING:
                values[f.name] = f.default
                continue
            if f.default_factory is not dataclasses.MISSING:
                values[f.name] = f.default_factory()
                continue
            raise MessageError(f"{where}: field '{f.name}' is missing")
        raw = fields[f.name]
        values[f.name] = _array(raw, spec, where, f.name, buffers) if spec.kind == "array" else raw
    msg = object.__new__(cls)
    for k, v in values.items():
        object.__setattr__(msg, k, v)
    validate(msg, where=where, strict=True)
    return msg


def decode_frames(frames: Sequence, expect: type | None = None, where: str = "message") -> tuple[Any, str]:
    """Decode bus frames ``[envelope, buffer, ...]``; returns ``(message, publisher)``.

    Frames may be bytes or ``zmq.Frame`` (arrays then view the frame's memory, no copy).
    """
    if not frames:
        raise MessageError(f"{where}: empty message (no frames)")
    env = _unpack(_as_buffer(frames[0]), where)
    publisher = env.get("publisher", "")
    if not isinstance(publisher, str):
        raise MessageError(f"{where}: 'publisher' must be a string")
    if publisher:
        where = f"{where} from {publisher!r}"
    return _build(env, list(frames[1:]), where, expect), publisher


def decode(blob: Any, expect: type | None = None, where: str = "message") -> Any:
    """Decode one msgpack blob written by :func:`encode`."""
    return _build(_unpack(blob, where), None, where, expect)
