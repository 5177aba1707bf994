"""Property tests of the wire format: every message type round-trips, corrupt bytes raise only DecodeError."""

import dataclasses
import math
import typing

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from shared import codec, messages
from shared.codec import DecodeError, Header

MESSAGE_CLASSES = [getattr(messages, name) for name in messages.__all__ if name != "Header"]
INT64 = st.integers(-(2**63), 2**63 - 1)
TEXT = st.text(max_size=12)
SETTINGS = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def test_every_registered_type_is_covered():
    assert set(MESSAGE_CLASSES) == set(codec.MESSAGE_TYPES.values())


def array_values(dtype: np.dtype, shape: tuple[int, ...]):
    elements = None
    if dtype.kind == "f":
        elements = st.floats(allow_nan=True, allow_infinity=True, width=8 * dtype.itemsize)
    return hnp.arrays(dtype, shape, elements=elements)


@st.composite
def messages_of(draw, cls):
    hints = typing.get_type_hints(cls)
    dims: dict[str, int] = {}

    def shape_of(spec_shape, local_dims):
        return tuple(d if isinstance(d, int) else local_dims.setdefault(d, draw(st.integers(0, 5))) for d in spec_shape)

    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name == "header":
            continue
        tp = hints[f.name]
        if "dtype" in f.metadata:
            dtype, spec_shape = f.metadata["dtype"], f.metadata["shape"]
            if typing.get_origin(tp) is tuple:  # a tuple of arrays, each with its own named dims
                n = draw(st.integers(0, 3))
                kwargs[f.name] = tuple(draw(array_values(dtype, shape_of(spec_shape, {}))) for _ in range(n))
            else:
                kwargs[f.name] = draw(array_values(dtype, shape_of(spec_shape, dims)))
        elif typing.get_origin(tp) is tuple:
            kwargs[f.name] = tuple(draw(st.lists(TEXT, max_size=4)))
        elif tp is int:
            kwargs[f.name] = draw(INT64)
        elif tp is float:
            kwargs[f.name] = draw(st.floats(allow_nan=True, allow_infinity=True))
        elif tp is bool:
            kwargs[f.name] = draw(st.booleans())
        else:
            kwargs[f.name] = draw(TEXT)
    header = Header(stamp_ns=draw(INT64), seq=draw(st.integers(0, 2**63 - 1)), frame_id=draw(TEXT))
    return cls(header=header, **kwargs)


ANY_MESSAGE = st.sampled_from(MESSAGE_CLASSES).flatmap(messages_of)


def assert_same(a, b):
    assert type(a) is type(b) and a.header == b.header
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape
            np.testing.assert_array_equal(x, y)  # NaN equals NaN here
        elif isinstance(x, tuple) and x and isinstance(x[0], np.ndarray):
            assert len(x) == len(y)
            for u, v in zip(x, y):
                assert u.dtype == v.dtype and u.shape == v.shape
                np.testing.assert_array_equal(u, v)
        elif isinstance(x, float) and math.isnan(x):
            assert math.isnan(y)
        else:
            assert x == y, f.name


@SETTINGS
@given(ANY_MESSAGE)
def test_round_trip_of_every_message_type(msg):
    data = codec.encode(msg)
    out = codec.decode(data, type(msg))
    assert_same(msg, out)
    assert codec.peek_type(data) is type(msg)
    # encode_into a larger (e.g. shared-memory) buffer gives the same bytes and decodes the same
    p = codec.plan(msg)
    buf = bytearray(p.size + 100)
    assert codec.encode_into(p, buf) == p.size == len(data)
    assert bytes(buf[: p.size]) == data
    assert_same(msg, codec.decode(memoryview(buf)[: p.size]))


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_random_bytes_raise_only_decode_error(data):
    for buf in (data, codec.MAGIC + bytes([codec.VERSION, 0]) + data):
        try:
            codec.decode(buf)
        except DecodeError:
            pass


@SETTINGS
@given(ANY_MESSAGE, st.data())
def test_truncated_or_corrupted_encodings_raise_only_decode_error(msg, data):
    enc = codec.encode(msg)
    cut = data.draw(st.integers(0, len(enc) - 1))
    try:
        out = codec.decode(enc[:cut])
    except DecodeError:
        pass
    else:  # only trailing padding was cut: the message is intact
        assert_same(msg, out)
    pos = data.draw(st.integers(0, len(enc) - 1))
    flipped = bytearray(enc)
    flipped[pos] ^= data.draw(st.integers(1, 255))
    try:
        codec.decode(bytes(flipped))
    except DecodeError:
        pass


@SETTINGS
@given(ANY_MESSAGE)
def test_wrong_expected_type_is_a_decode_error(msg):
    other = next(c for c in MESSAGE_CLASSES if c is not type(msg))
    try:
        codec.decode(codec.encode(msg), other)
    except DecodeError as exc:
        assert other.__name__ in str(exc)
    else:
        raise AssertionError("decoding as the wrong type succeeded")


def test_a_message_written_before_a_field_was_added_reads_with_the_default():
    """ServiceStats got counter_names / counter_values (with defaults) after recordings already held stats: such a
    message decodes, the new fields at their defaults; a field without a default stays required."""
    dropped = ("counter_names", "counter_values")
    old_fields = [(f.name, f.type, dataclasses.field(metadata=f.metadata))
                  for f in dataclasses.fields(messages.ServiceStats) if f.name != "header" and f.name not in dropped]
    Old = dataclasses.make_dataclass("ServiceStats", old_fields, bases=(codec.Message,), frozen=True, kw_only=True,
                                     namespace={"__module__": messages.__name__})
    Old.TYPE_ID = messages.ServiceStats.TYPE_ID  # the same wire id, as the older build wrote it
    e = np.zeros(0, np.int64)
    f = np.zeros(0)
    old = Old(header=Header(stamp_ns=5), service="depth", uptime_s=1.0, rss_mb=2.0, stage_names=(), stage_count=e,
              stage_rate_hz=f, stage_p50_ms=f, stage_p99_ms=f, stage_budget_ms=f, stage_overruns=e,
              queue_names=("q",), queue_received=np.array([3]), queue_dropped=np.array([1]), queue_depth=np.array([0]))
    got = codec.decode(codec.encode(old), messages.ServiceStats)
    assert got.service == "depth" and got.queue_dropped.tolist() == [1]
    assert got.counter_names == () and got.counter_values.shape == (0,)
    Older = dataclasses.make_dataclass("ServiceStats", [x for x in old_fields if x[0] != "rss_mb"],
                                       bases=(codec.Message,), frozen=True, kw_only=True,
                                       namespace={"__module__": messages.__name__})
    Older.TYPE_ID = messages.ServiceStats.TYPE_ID
    kwargs = {k: getattr(old, k) for k in [x[0] for x in old_fields] if k != "rss_mb"}
    try:
        codec.decode(codec.encode(Older(header=old.header, **kwargs)), messages.ServiceStats)
    except DecodeError as exc:
        assert "rss_mb" in str(exc)
    else:
        raise AssertionError("a message without a required field decoded")
