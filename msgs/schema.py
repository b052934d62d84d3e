"""Typed message machinery: field specs, the header, validation with clear errors.

A message type is a dataclass declared with :func:`message`; each field carries a spec
(:func:`array`, :func:`scalar`, :func:`text`, ...) that says what the wire may hold. Arrays
declare a dtype and a symbolic shape such as ``("K", "N")``: symbols bind across the fields of
one message, so ``data (K, N)`` and ``channel_offsets_m (K, 3)`` must agree on K.

Construction coerces arrays to the declared dtype when that is a same-kind cast (float64 to
float32, complex128 to complex64) and validates; decoding (msgs.codec) is strict: dtype and
shape must be exactly as declared, or :class:`MessageError` names the message, the field, what
was expected and what arrived.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from twinfocus.errors import TwinFocusError

if TYPE_CHECKING:
    from typing_extensions import dataclass_transform
else:

    def dataclass_transform(**_kwargs):
        """typing.dataclass_transform is Python 3.11+; it only informs type checkers."""
        return lambda f: f


class MessageError(TwinFocusError):
    """A message that does not match its schema (bad field, dtype, shape or encoding)."""


def now_ns() -> int:
    """Wall-clock time stamp, integer nanoseconds since the Unix epoch."""
    return time.time_ns()


@dataclass
class Header:
    """Every message's header (ROS ``std_msgs/Header`` plus a sequence number).

    stamp_ns : int, nanoseconds; the time the data describe (sensor time), not send time.
    seq : int, per topic and publisher, starting at 0; set by the publisher on send and used
        by subscribers to detect lost messages.
    frame_id : str, the coordinate frame the data are expressed in (e.g. ``"scene"``).
    """

    stamp_ns: int = 0
    seq: int = 0
    frame_id: str = ""

    def to_wire(self) -> list:
        return [int(self.stamp_ns), int(self.seq), str(self.frame_id)]

    @classmethod
    def from_wire(cls, value: Any, where: str) -> Header:
        if (
            not isinstance(value, (list, tuple))
            or len(value) != 3
            or not _is_int(value[0])
            or not _is_int(value[1])
            or not isinstance(value[2], str)
        ):
            raise MessageError(
                f"{where}: field 'header' must be [stamp_ns:int, seq:int, frame_id:str], got {value!r:.80}"
            )
        return cls(int(value[0]), int(value[1]), value[2])


# --- field specs ---------------------------------------------------------------------------


@dataclass(frozen=True)
class ArraySpec:
    dtype: np.dtype
    shapes: tuple[tuple, ...]  # alternatives; entries int (fixed) or str (symbol)
    optional: bool = False

    kind: ClassVar[str] = "array"

    def describe(self) -> str:
        alts = " or ".join("(" + ", ".join(str(d) for d in s) + (",)" if len(s) == 1 else ")") for s in self.shapes)
        return f"{self.dtype.name} array of shape {alts}" + (" or None" if self.optional else "")


@dataclass(frozen=True)
class ScalarSpec:
    pytype: (
        str  # "int" | "float" | "str" | "bool" | "list[str]" | "dict[str,float]" | "dict[str,int]" | "dict[str,str]"
    )

    kind: ClassVar[str] = "scalar"

    def describe(self) -> str:
        return self.pytype


def stamped() -> Any:
    """The ``header`` field: a fresh :class:`Header` unless one is given."""
    return field(default_factory=Header)


def array(dtype: Any, shape: tuple | list, *, optional: bool = False, doc: str = "") -> Any:
    """An ndarray field. ``shape`` is one tuple or a list of alternative tuples."""
    shapes = tuple(tuple(s) for s in shape) if isinstance(shape, list) else (tuple(shape),)
    spec = ArraySpec(np.dtype(dtype), shapes, optional)
    if optional:
        return field(default=None, metadata={"spec": spec, "doc": doc})
    return field(metadata={"spec": spec, "doc": doc})


def _scalar(pytype: str, default: Any, doc: str) -> Any:
    spec = ScalarSpec(pytype)
    if default is dataclasses.MISSING:
        return field(metadata={"spec": spec, "doc": doc})
    if isinstance(default, (list, dict)):
        # a fresh copy per message: a shared mutable default would leak between messages
        return field(default_factory=default.copy, metadata={"spec": spec, "doc": doc})
    return field(default=default, metadata={"spec": spec, "doc": doc})


def integer(default: Any = dataclasses.MISSING, doc: str = "") -> Any:
    return _scalar("int", default, doc)


def real(default: Any = dataclasses.MISSING, doc: str = "") -> Any:
    return _scalar("float", default, doc)


def text(default: Any = "", doc: str = "") -> Any:
    return _scalar("str", default, doc)


def flag(default: Any = False, doc: str = "") -> Any:
    return _scalar("bool", default, doc)


def strings(doc: str = "") -> Any:
    return _scalar("list[str]", [], doc)


def mapping(value_type: str, doc: str = "") -> Any:
    """A ``dict[str, value_type]`` field, value_type one of ``float``, ``int``, ``str``."""
    return _scalar(f"dict[str,{value_type}]", {}, doc)


# --- registry -------------------------------------------------------------------------------


class BusMessage:
    """What :func:`message` gives every message type, for type checkers: the message types
    derive from it. It holds no fields (it is no dataclass), so it changes no message's layout."""

    TYPE: ClassVar[str]  # the class name, the type's name on the wire
    TOPIC: ClassVar[str | None]  # the topic it normally travels on
    __dataclass_fields__: ClassVar[dict[str, Any]]  # set by dataclass() on each message type


#: message type name -> class, filled by :func:`message`
MESSAGE_TYPES: dict[str, type[BusMessage]] = {}


# Tells type checkers that message types take their fields as keywords (names and value types
# checked at call sites); the field helpers above return Any, so every field counts as defaulted.
@dataclass_transform(kw_only_default=True)
def message(topic: str | None = None):
    """Class decorator: make a dataclass message type and register it under its class name.

    ``topic`` is the topic this type normally travels on (docs/architecture.md section 4).
    """

    def wrap(cls):
        def __post_init__(self):
            _coerce_and_validate(self, strict=False, where=f"{cls.__name__} message")

        # dataclass() only calls __post_init__ if it exists when the class is processed.
        cls.__post_init__ = __post_init__
        if "header" not in cls.__dict__:
            cls.header = stamped()
        # Keyword-only: required fields may follow fields with defaults, and call sites name
        # every field (RadarFrame(data=..., f0_hz=...)), which reads better for wide messages.
        cls = dataclass(cls, kw_only=True)
        names = [f.name for f in dataclasses.fields(cls)]
        if not names or names[0] != "header":
            raise TypeError(f"{cls.__name__}: the first field must be 'header'")
        cls.TYPE = cls.__name__
        cls.TOPIC = topic
        MESSAGE_TYPES[cls.__name__] = cls
        return cls

    return wrap


def field_specs(cls) -> list[tuple[str, Any]]:
    """(name, spec) of every field after the header, in declaration order."""
    return [(f.name, f.metadata["spec"]) for f in dataclasses.fields(cls) if f.name != "header"]


def schema_of(cls) -> dict:
    """A plain description of a message type (for MCAP channel metadata and ``topic list``)."""
    out = {"type": cls.TYPE, "topic": cls.TOPIC, "fields": {"header": "[stamp_ns:int, seq:int, frame_id:str]"}}
    for name, spec in field_specs(cls):
        out["fields"][name] = spec.describe()
    return out


# --- validation -----------------------------------------------------------------------------


def _is_int(v: Any) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_))


def _check_scalar(spec: ScalarSpec, value: Any, where: str, name: str, strict: bool) -> Any:
    t = spec.pytype

    def bad():
        return MessageError(f"{where}: field '{name}' must be {t}, got {type(value).__name__} {value!r:.60}")

    if t == "int":
        if not _is_int(value):
            raise bad()
        return int(value)
    if t == "float":
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
            raise bad()
        return float(value)
    if t == "str":
        if not isinstance(value, str):
            raise bad()
        return value
    if t == "bool":
        if not isinstance(value, (bool, np.bool_)):
            raise bad()
        return bool(value)
    if t == "list[str]":
        if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):
            raise bad()
        return list(value)
    if t.startswith("dict[str,"):
        vt = t[len("dict[str,") : -1]
        if not isinstance(value, dict) or not all(isinstance(k, str) for k in value):
            raise bad()
        sub = ScalarSpec(vt)
        return {k: _check_scalar(sub, v, where, f"{name}[{k!r}]", strict) for k, v in value.items()}
    raise TypeError(f"unknown scalar spec {t}")  # pragma: no cover - a bug in a message declaration


def _check_array(spec: ArraySpec, value: Any, where: str, name: str, strict: bool, dims: dict) -> Any:
    if value is None:
        if spec.optional:
            return None
        raise MessageError(f"{where}: field '{name}' is missing (expected {spec.describe()})")
    if strict:
        if not isinstance(value, np.ndarray) or value.dtype != spec.dtype:
            got = f"{value.dtype.name} {value.shape}" if isinstance(value, np.ndarray) else type(value).__name__
            raise MessageError(f"{where}: field '{name}' must be {spec.describe()}, got {got}")
    else:
        a = np.asarray(value)
        if a.dtype != spec.dtype:
            if a.dtype == object or not np.can_cast(a.dtype, spec.dtype, casting="same_kind"):
                raise MessageError(
                    f"{where}: field '{name}' must be {spec.describe()}, got dtype {a.dtype.name} (no safe cast)"
                )
            a = a.astype(spec.dtype)
        value = a
    # Shape: the first alternative whose rank matches decides; symbols must agree across fields.
    for shape in spec.shapes:
        if len(shape) != value.ndim:
            continue
        trial = dict(dims)
        ok = True
        for want, got in zip(shape, value.shape):
            if isinstance(want, int):
                ok = ok and want == got
            elif want in trial:
                ok = ok and trial[want] == got
            else:
                trial[want] = got
        if ok:
            dims.update(trial)
            return value
    known = {k: v for k, v in dims.items()}
    hint = f" (already bound: {', '.join(f'{k}={v}' for k, v in known.items())})" if known else ""
    raise MessageError(f"{where}: field '{name}' must be {spec.describe()}, got shape {value.shape}{hint}")


def _coerce_and_validate(msg: Any, strict: bool, where: str) -> None:
    if not isinstance(msg.header, Header):
        raise MessageError(f"{where}: field 'header' must be a Header, got {type(msg.header).__name__}")
    dims: dict[str, int] = {}
    for name, spec in field_specs(type(msg)):
        value = getattr(msg, name)
        if spec.kind == "array":
            value = _check_array(spec, value, where, name, strict, dims)
        else:
            value = _check_scalar(spec, value, where, name, strict)
        object.__setattr__(msg, name, value)
    check = getattr(msg, "check", None)
    if check is not None:
        problem = check()
        if problem:
            raise MessageError(f"{where}: {problem}")


def validate(msg: Any, where: str | None = None, strict: bool = True) -> None:
    """Check a message against its declared schema; raise :class:`MessageError` if it does not fit."""
    _coerce_and_validate(msg, strict=strict, where=where or f"{type(msg).__name__} message")
