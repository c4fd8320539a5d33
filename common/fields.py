"""Field validators for messages: each checks one value and returns it normalised (lists -> tuples,
ints -> floats where a float is meant). They raise MessageError naming the field, nothing else.

Each validator also records the msgspec type that accepts exactly what it accepts (`wire_type`), so
that `common/fastdecode.py` can decode and validate a message in C; the checks here stay the reference
(construction, and every message the fast path refuses), and a differential test holds the two equal.
"""

from __future__ import annotations

import enum
import math
import sys
from collections.abc import Callable, Collection
from typing import Annotated, Any, Literal, TypeVar

import msgspec

from dynqos.common.errors import KeyExprError, MessageError
from dynqos.common.keys import check_uav_id

Validator = Callable[[str, Any], Any]
E = TypeVar("E", bound=enum.Enum)

INT64_MAX = 2**63 - 1
FLOAT_MAX = sys.float_info.max  # a finite bound on both sides keeps inf and NaN out of msgspec's floats

_WIRE: dict[Validator, Any] = {}


def wire_type(check: Validator) -> Any:
    """The msgspec type that accepts what `check` accepts (KeyError for a validator without one)."""
    return _WIRE[check]


def _typed(check: Validator, tp: Any) -> Validator:
    _WIRE[check] = tp
    return check


def _float(lo: float, hi: float) -> Any:
    return Annotated[float, msgspec.Meta(ge=max(lo, -FLOAT_MAX), le=min(hi, FLOAT_MAX))]


def uav_id(name: str, value: Any) -> str:
    try:
        return check_uav_id(value)
    except KeyExprError as exc:
        raise MessageError(name, str(exc)) from None


# \Z, not $: msgspec searches with `re`, where $ also matches before a final newline
_typed(uav_id, Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z0-9_-]{1,32}\Z")])


def integer(lo: int = 0, hi: int = INT64_MAX) -> Validator:
    def check(name: str, value: Any) -> int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise MessageError(name, f"expected an integer, got {type(value).__name__}")
        if not lo <= value <= hi:
            raise MessageError(name, f"{value} is outside [{lo}, {hi}]")
        return value

    return _typed(check, Annotated[int, msgspec.Meta(ge=lo, le=hi)])


def real(lo: float = -math.inf, hi: float = math.inf) -> Validator:
    def check(name: str, value: Any) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise MessageError(name, f"expected a number, got {type(value).__name__}")
        number = float(value)
        if not math.isfinite(number):
            raise MessageError(name, f"expected a finite number, got {number}")
        if not lo <= number <= hi:
            raise MessageError(name, f"{number:g} is outside [{lo:g}, {hi:g}]")
        return number

    return _typed(check, _float(lo, hi))


def boolean(name: str, value: Any) -> bool:
    if not isinstance(value, bool):
        raise MessageError(name, f"expected true or false, got {type(value).__name__}")
    return value


_typed(boolean, bool)


def text(max_len: int) -> Validator:
    def check(name: str, value: Any) -> str:
        if not isinstance(value, str):
            raise MessageError(name, f"expected a string, got {type(value).__name__}")
        if len(value) > max_len:
            raise MessageError(name, f"string of {len(value)} characters exceeds {max_len}")
        return value

    return _typed(check, Annotated[str, msgspec.Meta(max_length=max_len)])


def choice(options: Collection[str]) -> Validator:
    allowed = frozenset(options)

    def check(name: str, value: Any) -> str:
        if not isinstance(value, str) or value not in allowed:
            shown = value[:40] if isinstance(value, str) else type(value).__name__
            raise MessageError(name, f"{shown!r} is not one of {sorted(allowed)}")
        return value

    return _typed(check, Literal[tuple(sorted(allowed))])


def member(kind: type[E]) -> Validator:
    """A value of the str enum `kind` (given as the enum or its plain value), returned as the member."""
    allowed = sorted(m.value for m in kind)

    def check(name: str, value: Any) -> E:
        try:
            return kind(value)
        except ValueError:
            shown = value[:40] if isinstance(value, str) else type(value).__name__
            raise MessageError(name, f"{shown!r} is not one of {allowed}") from None

    return _typed(check, kind)


def blob(max_len: int) -> Validator:
    def check(name: str, value: Any) -> bytes:
        if not isinstance(value, (bytes, bytearray, memoryview)):
            raise MessageError(name, f"expected bytes, got {type(value).__name__}")
        if len(value) > max_len:
            raise MessageError(name, f"{len(value)} bytes exceed the limit of {max_len}")
        return bytes(value) if not isinstance(value, bytes) else value

    return _typed(check, Annotated[bytes, msgspec.Meta(max_length=max_len)])


def optional(inner: Validator) -> Validator:
    def check(name: str, value: Any) -> Any:
        return None if value is None else inner(name, value)

    return _typed(check, wire_type(inner) | None)


def sequence(item: Validator, min_len: int = 0, max_len: int = 1 << 16) -> Validator:
    def check(name: str, value: Any) -> tuple[Any, ...]:
        if not isinstance(value, (list, tuple)):
            raise MessageError(name, f"expected a list, got {type(value).__name__}")
        if not min_len <= len(value) <= max_len:
            raise MessageError(name, f"length {len(value)} is outside [{min_len}, {max_len}]")
        try:
            return tuple(item(name, v) for v in value)
        except MessageError:  # rare: check again, naming the element (f-strings per item cost)
            return tuple(item(f"{name}[{i}]", v) for i, v in enumerate(value))

    items: Any = tuple[wire_type(item), ...]  # type: ignore[misc]
    return _typed(check, Annotated[items, msgspec.Meta(min_length=min_len, max_length=max_len)])


def vector(length: int, lo: float = -math.inf, hi: float = math.inf) -> Validator:
    """A fixed-length list of finite reals in [lo, hi]. The common case, plain floats in range, takes
    one comparison each (the MPC validates every Command it builds); anything else gets `real`'s
    full check and its error message."""
    slow = sequence(real(lo, hi), length, length)

    def check(name: str, value: Any) -> tuple[float, ...]:
        # v - v == 0.0 is False for inf and NaN; NaN also fails the range test.
        if (
            isinstance(value, (list, tuple))
            and len(value) == length
            and all(type(v) is float and lo <= v <= hi and v - v == 0.0 for v in value)
        ):
            return tuple(value)
        return slow(name, value)  # type: ignore[no-any-return]

    return _typed(check, tuple[(_float(lo, hi),) * length])  # type: ignore[misc]


def record(*items: Validator) -> Validator:
    """A fixed-length list whose i-th element passes `items[i]` (a small record on the wire)."""

    def check(name: str, value: Any) -> tuple[Any, ...]:
        if not isinstance(value, (list, tuple)) or len(value) != len(items):
            shown = len(value) if isinstance(value, (list, tuple)) else type(value).__name__
            raise MessageError(name, f"expected a list of {len(items)} items, got {shown}")
        return tuple(item(f"{name}[{i}]", v) for i, (item, v) in enumerate(zip(items, value, strict=True)))

    return _typed(check, tuple[tuple(wire_type(item) for item in items)])  # type: ignore[misc]
