"""Wire format of sigmaslam messages: a small header plus raw array buffers.

Layout of one encoded message (all integers little-endian)::

    offset 0   b"SGMS"                 magic
    offset 4   u8  format version (1)
    offset 5   u8  reserved (0)
    offset 6   u16 message type id
    offset 8   u32 length M of the meta block
    offset 12  M bytes of UTF-8 JSON: {"s": {scalar fields}, "a": [[field, item, dtype, shape, offset, nbytes], ...]}
    ...        padding to a multiple of 64
    data       the arrays' raw C-order bytes, each starting at a multiple of 64 from the data start

The JSON block holds only scalars (stamps, ids, names) and array descriptors, never array contents.
Decoding is zero-copy (arrays are read-only views of the buffer) and validates everything it reads:
a truncated, corrupt or foreign buffer raises :class:`DecodeError`, never anything else.
"""

from __future__ import annotations

import dataclasses
import json
import math
import struct
import typing
from typing import Any, ClassVar

import numpy as np

MAGIC = b"SGMS"
VERSION = 1
NATIVE_ENCODING = "sigmaslam-codec-v1"  # these bytes as an MCAP message/schema encoding (recorder writes, player reads)
_PREFIX = struct.Struct("<4sBBHI")
ALIGN = 64
# dtypes allowed on the wire (a decoder never builds object arrays)
_WIRE_DTYPES = {np.dtype(n).str: np.dtype(n) for n in (
    "uint8", "int8", "uint16", "int16", "uint32", "int32", "uint64", "int64", "float16", "float32", "float64", "bool")}
_MAX_META = 1 << 20

MESSAGE_TYPES: dict[int, type[Message]] = {}


class DecodeError(ValueError):
    """Bytes that are not a valid sigmaslam message (truncated, corrupt, unknown type, bad shapes)."""


class MessageError(ValueError):
    """A message constructed with a field of the wrong dtype, shape or type."""


def array_field(doc: str, dtype: str, shape: tuple[int | str, ...], **kwargs: Any) -> Any:
    """An ndarray field: ``shape`` entries are ints (fixed) or names shared by fields of one message."""
    return dataclasses.field(metadata={"doc": doc, "dtype": np.dtype(dtype), "shape": tuple(shape)}, **kwargs)


def scalar_field(doc: str, **kwargs: Any) -> Any:
    return dataclasses.field(metadata={"doc": doc}, **kwargs)


@dataclasses.dataclass(frozen=True, kw_only=True)
class Header:
    """Common header: sensor or event time, per-publisher sequence number, frame the data is in."""

    stamp_ns: int = scalar_field("time the data refers to [ns], int64")
    seq: int = scalar_field("per-publisher sequence number, starts at 0", default=0)
    frame_id: str = scalar_field("frame of the data, e.g. 'W', 'S', 'cam0'", default="")


@dataclasses.dataclass(frozen=True, kw_only=True)
class Message:
    """Base of all messages: frozen, keyword-only, validated on construction."""

    TYPE_ID: ClassVar[int] = 0
    header: Header

    def __post_init__(self) -> None:
        _validate(self)


def register(type_id: int):
    """Class decorator that gives a message type its wire id (unique, 1..65535)."""

    def wrap(cls: type[Message]) -> type[Message]:
        if not 0 < type_id < 65536:
            raise ValueError(f"type id {type_id} out of range")
        if type_id in MESSAGE_TYPES and MESSAGE_TYPES[type_id] is not cls:
            raise ValueError(f"type id {type_id} already used by {MESSAGE_TYPES[type_id].__name__}")
        cls.TYPE_ID = type_id
        MESSAGE_TYPES[type_id] = cls
        _SPECS.pop(cls, None)
        return cls

    return wrap


# ----------------------------------------------------------------------------- field specs

@dataclasses.dataclass(frozen=True)
class _FieldSpec:
    name: str
    kind: str  # "array", "arrays" (tuple of arrays), "scalar", "strings"
    py_type: Any = None
    dtype: np.dtype | None = None
    shape: tuple[int | str, ...] = ()


_SPECS: dict[type, tuple[_FieldSpec, ...]] = {}
_DEFAULTED: dict[type, frozenset[str]] = {}  # fields a message type declares with a default


def _defaulted(cls: type) -> frozenset[str]:
    out = _DEFAULTED.get(cls)
    if out is None:
        out = _DEFAULTED[cls] = frozenset(f.name for f in dataclasses.fields(cls) if (
            f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING))
    return out


def _specs(cls: type) -> tuple[_FieldSpec, ...]:
    cached = _SPECS.get(cls)
    if cached is not None:
        return cached
    hints = typing.get_type_hints(cls)
    out = []
    for f in dataclasses.fields(cls):
        if f.name == "header":
            continue
        tp = hints[f.name]
        if "dtype" in f.metadata:
            kind = "arrays" if typing.get_origin(tp) is tuple else "array"
            out.append(_FieldSpec(f.name, kind, None, f.metadata["dtype"], f.metadata["shape"]))
        elif typing.get_origin(tp) is tuple:
            out.append(_FieldSpec(f.name, "strings", str))
        elif tp in (int, float, str, bool):
            out.append(_FieldSpec(f.name, "scalar", tp))
        else:
            raise TypeError(f"{cls.__name__}.{f.name}: unsupported message field type {tp}")
    _SPECS[cls] = tuple(out)
    return _SPECS[cls]


def _check_array(cls_name: str, spec: _FieldSpec, value: Any, dims: dict[str, int]) -> np.ndarray:
    where = f"{cls_name}.{spec.name}"
    if not isinstance(value, np.ndarray):
        raise MessageError(f"{where}: expected numpy array of {spec.dtype}, got {type(value).__name__}")
    if value.dtype != spec.dtype:
        if not np.can_cast(value.dtype, spec.dtype, "safe"):
            raise MessageError(f"{where}: dtype {value.dtype} cannot be stored losslessly as {spec.dtype}")
        value = value.astype(spec.dtype)
    if value.ndim != len(spec.shape):
        raise MessageError(f"{where}: expected shape {spec.shape}, got {value.shape}")
    for axis, (want, got) in enumerate(zip(spec.shape, value.shape)):
        if isinstance(want, int):
            if want != got:
                raise MessageError(f"{where}: axis {axis} must be {want}, got shape {value.shape}")
        elif dims.setdefault(want, got) != got:
            raise MessageError(f"{where}: axis {axis} ('{want}') is {got} but {dims[want]} elsewhere in the message")
    return value


def _validate(msg: Message) -> None:
    cls = type(msg)
    if not isinstance(msg.header, Header):
        raise MessageError(f"{cls.__name__}.header must be a Header")
    if not isinstance(msg.header.stamp_ns, (int, np.integer)) or isinstance(msg.header.stamp_ns, bool):
        raise MessageError(f"{cls.__name__}.header.stamp_ns must be an integer [ns]")
    dims: dict[str, int] = {}
    for spec in _specs(cls):
        value = getattr(msg, spec.name)
        if spec.kind == "array":
            checked = _check_array(cls.__name__, spec, value, dims)
            if checked is not value:
                object.__setattr__(msg, spec.name, checked)
        elif spec.kind == "arrays":
            if not isinstance(value, (tuple, list)):
                raise MessageError(f"{cls.__name__}.{spec.name}: expected a tuple of arrays")
            # each item has its own named dimensions (e.g. cameras of different sizes)
            items = tuple(_check_array(cls.__name__, spec, v, {}) for v in value)
            object.__setattr__(msg, spec.name, items)
        elif spec.kind == "strings":
            if not isinstance(value, (tuple, list)) or not all(isinstance(s, str) for s in value):
                raise MessageError(f"{cls.__name__}.{spec.name}: expected a tuple of strings")
            object.__setattr__(msg, spec.name, tuple(value))
        else:
            ok = isinstance(value, spec.py_type) and not (spec.py_type is int and isinstance(value, bool))
            if spec.py_type is float and isinstance(value, (int, np.floating, np.integer)) and not isinstance(value, bool):
                object.__setattr__(msg, spec.name, float(value))
                ok = True
            if spec.py_type is int and isinstance(value, np.integer):
                object.__setattr__(msg, spec.name, int(value))
                ok = True
            if not ok:
                raise MessageError(f"{cls.__name__}.{spec.name}: expected {spec.py_type.__name__}, got {value!r}")


# ----------------------------------------------------------------------------- encoding

def _align(n: int) -> int:
    return (n + ALIGN - 1) // ALIGN * ALIGN


@dataclasses.dataclass
class EncodePlan:
    """What :func:`encode_into` writes: computed once so a caller can size a (shared-memory) buffer."""

    prefix_and_meta: bytes
    data_start: int
    arrays: list[tuple[int, np.ndarray]]  # (offset from data start, C-contiguous array)
    size: int


def plan(msg: Message) -> EncodePlan:
    cls = type(msg)
    if cls.TYPE_ID not in MESSAGE_TYPES:
        raise MessageError(f"{cls.__name__} is not a registered message type")
    h = msg.header
    scalars: dict[str, Any] = {"header": [int(h.stamp_ns), int(h.seq), h.frame_id]}
    descs = []
    arrays = []
    cursor = 0

    def add(name: str, item: int, arr: np.ndarray) -> None:
        nonlocal cursor
        arr = np.ascontiguousarray(arr)
        descs.append([name, item, arr.dtype.str, list(arr.shape), cursor, arr.nbytes])
        arrays.append((cursor, arr))
        cursor = _align(cursor + arr.nbytes)

    for spec in _specs(cls):
        value = getattr(msg, spec.name)
        if spec.kind == "array":
            add(spec.name, -1, value)
        elif spec.kind == "arrays":
            scalars[spec.name] = len(value)
            for i, arr in enumerate(value):
                add(spec.name, i, arr)
        elif spec.kind == "strings":
            scalars[spec.name] = list(value)
        else:
            scalars[spec.name] = value
    meta = json.dumps({"s": scalars, "a": descs}, separators=(",", ":")).encode()
    head = _PREFIX.pack(MAGIC, VERSION, 0, cls.TYPE_ID, len(meta)) + meta
    data_start = _align(len(head))
    return EncodePlan(head, data_start, arrays, data_start + cursor)


def encode_into(p: EncodePlan, out: memoryview | bytearray) -> int:
    """Write a planned message into ``out`` (at least ``p.size`` bytes); returns bytes written."""
    view = memoryview(out).cast("B")
    if len(view) < p.size:
        raise ValueError(f"buffer of {len(view)} bytes is smaller than the message ({p.size})")
    n = len(p.prefix_and_meta)
    view[:n] = p.prefix_and_meta
    view[n:p.data_start] = bytes(p.data_start - n)
    for offset, arr in p.arrays:
        start = p.data_start + offset
        if arr.nbytes:
            view[start:start + arr.nbytes] = arr.reshape(-1).view(np.uint8)
    return p.size


def encode(msg: Message) -> bytes:
    p = plan(msg)
    buf = bytearray(p.size)
    encode_into(p, buf)
    return bytes(buf)


# ----------------------------------------------------------------------------- decoding

def peek_type(buf: bytes | bytearray | memoryview) -> type[Message]:
    """Message class of an encoded buffer, from its prefix only."""
    view = memoryview(buf).cast("B")
    if len(view) < _PREFIX.size:
        raise DecodeError(f"buffer of {len(view)} bytes is shorter than the {_PREFIX.size}-byte prefix")
    magic, version, _, type_id, _ = _PREFIX.unpack_from(view, 0)
    if magic != MAGIC:
        raise DecodeError(f"bad magic {bytes(magic)!r}: not a sigmaslam message")
    if version != VERSION:
        raise DecodeError(f"unsupported format version {version} (this build reads {VERSION})")
    cls = MESSAGE_TYPES.get(type_id)
    if cls is None:
        raise DecodeError(f"unknown message type id {type_id}")
    return cls


def decode(buf: bytes | bytearray | memoryview, expect: type[Message] | None = None) -> Message:
    """Decode one message; arrays are read-only views of ``buf``. Raises :class:`DecodeError`."""
    view = memoryview(buf).cast("B")
    cls = peek_type(view)
    if expect is not None and cls is not expect:
        raise DecodeError(f"expected {expect.__name__}, got {cls.__name__}")
    meta_len = _PREFIX.unpack_from(view, 0)[4]
    meta_end = _PREFIX.size + meta_len
    if meta_len > _MAX_META or meta_end > len(view):
        raise DecodeError(f"meta block of {meta_len} bytes exceeds the buffer ({len(view)} bytes)")
    try:
        meta = json.loads(bytes(view[_PREFIX.size:meta_end]))
        scalars, descs = meta["s"], meta["a"]
        stamp_ns, seq, frame_id = scalars.pop("header")
    except (ValueError, KeyError, TypeError) as exc:
        raise DecodeError(f"corrupt meta block: {exc}") from exc
    if not isinstance(descs, list) or not isinstance(scalars, dict):
        raise DecodeError("corrupt meta block: wrong structure")
    data_start = _align(meta_end)
    kwargs: dict[str, Any] = {}
    specs = {s.name: s for s in _specs(cls)}
    tuples: dict[str, list[Any]] = {}
    for name, spec in specs.items():
        if spec.kind == "arrays":
            count = scalars.pop(name, None)
            if not isinstance(count, int) or isinstance(count, bool) or not 0 <= count <= 4096:
                raise DecodeError(f"{cls.__name__}.{name}: bad item count {count!r}")
            tuples[name] = [None] * count
    for desc in descs:
        try:
            name, item, dtype_str, shape, offset, nbytes = desc
        except (TypeError, ValueError) as exc:
            raise DecodeError(f"corrupt array descriptor {desc!r}") from exc
        spec = specs.get(name) if isinstance(name, str) else None
        if spec is None or spec.kind not in ("array", "arrays"):
            raise DecodeError(f"{cls.__name__}: unexpected array field {name!r}")
        dtype = _WIRE_DTYPES.get(dtype_str) if isinstance(dtype_str, str) else None
        if dtype is None or dtype != spec.dtype:
            raise DecodeError(f"{cls.__name__}.{name}: dtype {dtype_str!r}, expected {spec.dtype}")
        if (not isinstance(shape, list) or not all(isinstance(d, int) and not isinstance(d, bool) and d >= 0 for d in shape)
                or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in (offset, nbytes))):
            raise DecodeError(f"{cls.__name__}.{name}: bad shape/offset {shape!r}/{offset!r}")
        count = math.prod(shape)
        if count * dtype.itemsize != nbytes:
            raise DecodeError(f"{cls.__name__}.{name}: {nbytes} bytes do not hold shape {shape} of {dtype}")
        start = data_start + offset
        if start + nbytes > len(view):
            raise DecodeError(f"{cls.__name__}.{name}: truncated ({start + nbytes} > {len(view)} bytes)")
        arr = np.frombuffer(view, dtype=dtype, count=count, offset=start).reshape(shape)
        if spec.kind == "array":
            if name in kwargs:
                raise DecodeError(f"{cls.__name__}.{name}: given twice")
            kwargs[name] = arr
        else:
            slots = tuples[name]
            if not isinstance(item, int) or not 0 <= item < len(slots) or slots[item] is not None:
                raise DecodeError(f"{cls.__name__}.{name}: bad item index {item!r}")
            slots[item] = arr
    for name, slots in tuples.items():
        if any(s is None for s in slots):
            raise DecodeError(f"{cls.__name__}.{name}: missing items")
        kwargs[name] = tuple(slots)
    for name, value in scalars.items():
        spec = specs.get(name)
        if spec is None or spec.kind not in ("scalar", "strings"):
            raise DecodeError(f"{cls.__name__}: unexpected field {name!r}")
        kwargs[name] = value
    missing = set(specs) - set(kwargs) - _defaulted(cls)
    if missing:  # a field added with a default may be absent (a message written before it existed): the default
        raise DecodeError(f"{cls.__name__}: missing field(s) {sorted(missing)}")
    try:
        header = Header(stamp_ns=stamp_ns, seq=seq, frame_id=frame_id)
        if not isinstance(stamp_ns, int) or not isinstance(seq, int) or not isinstance(frame_id, str):
            raise MessageError("bad header types")
        return cls(header=header, **kwargs)
    except (MessageError, TypeError) as exc:
        raise DecodeError(f"{cls.__name__}: {exc}") from exc
