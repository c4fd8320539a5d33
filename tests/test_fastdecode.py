"""The fast decoder (msgspec, common/fastdecode.py) against the reference one (Python validators).

The fast path may refuse what the reference accepts (it then costs a second decode, never a wrong
answer), but it must accept every valid message, and whatever it accepts the reference must accept
as the same message, value for value and type for type.
"""

from __future__ import annotations

from dataclasses import fields
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dynqos.common import message_base as base
from dynqos.common import messages as m
from dynqos.common.errors import DecodeError, MessageError
from dynqos.common.modes import Flow, Grant
from tests.test_messages import any_message

# What a broken or hostile sender may put in a field: every msgpack type, edge values included.
scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**63), 2**64 - 1),
    st.floats(),  # nan and infinities included
    st.sampled_from([0.0, -0.0, 1e-7, 1.0001, 1e6, 1e300]),
    st.text(max_size=40),
    st.sampled_from(["uav1\n", "", "x" * 33, "LL", "rgb", "jpeg", "q1", "priority", "edge", "none"]),
    st.binary(max_size=16),
)
values = st.recursive(scalars, lambda inner: st.lists(inner, max_size=5), max_leaves=12)


def _reference(data: bytes) -> m.Message | None:
    try:
        return m.decode_checked(data)
    except DecodeError:
        return None


def _same(fast: m.Message, reference: m.Message) -> None:
    assert type(fast) is type(reference)
    assert m.encode(fast) == m.encode(reference)  # msgpack keeps int and float apart: types match too


@settings(max_examples=300)
@given(any_message)
def test_every_valid_message_takes_the_fast_path_and_decodes_the_same(message: m.Message) -> None:
    data = m.encode(message)
    fast = m._FAST.decode(data)
    assert fast is not None, message
    _same(fast, message)
    _same(fast, m.decode_checked(data))


@settings(max_examples=800)
@given(any_message, st.data())
def test_what_the_fast_path_accepts_the_reference_accepts_as_the_same_message(
    message: m.Message, data: st.DataObject
) -> None:
    body: dict[Any, Any] = msgpack.unpackb(m.encode(message))
    names = sorted(body)
    for name in data.draw(st.lists(st.sampled_from(names), max_size=3, unique=True)):
        if data.draw(st.booleans()):
            body[name] = data.draw(values)
        else:
            del body[name]
    if data.draw(st.booleans()):
        body[data.draw(st.sampled_from(["extra", "T", 1, b"t"]))] = data.draw(values)
    packed = msgpack.packb(body, use_bin_type=True)
    fast = m._FAST.decode(packed)
    reference = _reference(packed)
    if fast is not None:
        assert reference is not None, (body, fast)
        _same(fast, reference)
    if reference is None:
        assert fast is None
    assert (m.decode(packed) if reference is not None else None) == reference


def test_a_refused_message_still_names_its_field() -> None:
    body = msgpack.unpackb(m.encode(m.CameraAck(uav="uav1", seq=1, frame_seq=2, kind="rgb", stamp_ns=3,
                                                 edge_hold_ns=4)))  # fmt: skip
    body["kind"] = "thermal"
    with pytest.raises(DecodeError) as refused:
        m.decode(msgpack.packb(body))
    assert refused.value.field == "kind"


# What a caller may hand a constructor beside wire values: numpy scalars, enum members, bytearrays.
arguments = st.one_of(
    values,
    st.floats(-10, 10).map(np.float64),
    st.sampled_from([Flow.PRIORITY, Grant.AVAILABLE, bytearray(b"ab"), memoryview(b"cd"), (1, 2, 3)]),
    st.sampled_from([[0.5, 1, True], "", "dGV4dA==", "1", "1.5", 1.0, 2**63, -1]),  # coercions to refuse
)


def _construct(cls: type[m.Message], kwargs: dict[str, Any], *, fast: bool) -> tuple[str, Any]:
    base.CONSTRUCTION.enabled = fast
    try:
        return "ok", m.encode(cls(**kwargs))
    except MessageError as exc:
        return "refused", exc.field
    finally:
        base.CONSTRUCTION.enabled = True


@settings(max_examples=1200)
@given(any_message, st.data())
def test_construction_in_c_accepts_refuses_and_normalises_as_the_validators_do(
    message: m.Message, data: st.DataObject
) -> None:
    kwargs = {field.name: getattr(message, field.name) for field in fields(message)}
    for name in data.draw(st.lists(st.sampled_from(sorted(kwargs)), max_size=3, unique=True)):
        old = kwargs[name]
        kwargs[name] = data.draw(st.just(list(old)) if isinstance(old, tuple) else arguments)
    assert _construct(type(message), kwargs, fast=True) == _construct(type(message), kwargs, fast=False)
