"""Decode and validate a message in C: msgspec structs built from each message's own SCHEMA.

Decoding used to be most of what an edge service did around its work: msgpack to a dict, then one
Python validator call per field and per vector element (12 us for a State, where the MPC's solve takes
a few hundred). msgspec decodes straight into a struct whose types carry the same bounds, lengths,
choices and patterns (each validator in `common/fields.py` records its msgspec type), in about 1 us.

It is a fast path, not a second definition: it accepts a message only if every field passes, and then
the message's cross-field `_check` runs as it always does. Anything it refuses goes to the reference
decoder (`messages.decode_checked`), which either accepts it too or raises the DecodeError that names
the field, so what a sender sees on bad input does not change. `tests/test_fastdecode.py` holds the
two paths equal on generated valid and broken messages.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Literal, Union

import msgspec

from dynqos.common import fields as f
from dynqos.common.errors import MessageError

# Types convert() takes as they are: without this it would read a str given for a bytes field as base64.
_NATIVE = (bytes, bytearray, memoryview)


def _struct(cls: type[Any], version: int) -> type[msgspec.Struct]:
    """The struct for `cls`: its tag `t`, the version `v`, and each field with the type its validator
    accepts (and the dataclass's default where it has one)."""
    specs: list[tuple[str, Any] | tuple[str, Any, Any]] = [("v", Literal[version])]
    for field in dataclasses.fields(cls):
        tp = f.wire_type(cls.SCHEMA[field.name])
        if field.default is not dataclasses.MISSING:
            specs.append((field.name, tp, field.default))
        elif field.default_factory is not dataclasses.MISSING:
            specs.append((field.name, tp, msgspec.field(default_factory=field.default_factory)))
        else:
            specs.append((field.name, tp))
    return msgspec.defstruct(
        f"Wire{cls.TYPE}", specs, tag_field="t", tag=cls.TYPE, forbid_unknown_fields=True, kw_only=True
    )


class FastDecoder:
    """msgspec's decoder over every message type (a union tagged by `t`)."""

    def __init__(self, message_types: dict[str, type[Any]], version: int) -> None:
        structs = {_struct(cls, version): cls for cls in message_types.values()}
        self._class_of: dict[type[msgspec.Struct], type[Any]] = structs
        self._struct_of = {cls: struct for struct, cls in structs.items()}
        self._version = version
        self._names = {
            struct: tuple(field.name for field in dataclasses.fields(cls)) for struct, cls in structs.items()
        }
        union = Union[tuple(structs)]  # type: ignore[valid-type]  # noqa: UP007 (a union built at run time)
        self._decoder = msgspec.msgpack.Decoder(union)

    def normalise(self, message: Any) -> bool:
        """Check and normalise a message being constructed, in C (lists to tuples, ints to floats,
        values to enum members); False where anything is off, and its fields are then untouched (the
        Python validators run and name the field)."""
        kind = self._struct_of[type(message)]
        values = {name: getattr(message, name) for name in self._names[kind]}
        values["v"] = self._version
        try:
            struct = msgspec.convert(values, kind, builtin_types=_NATIVE)
        except Exception:  # ValidationError; a value msgspec does not take (numpy scalars) goes slow
            return False
        self._fill(message, struct)
        return True

    def decode(self, data: bytes | bytearray | memoryview) -> Any | None:
        """The message, or None where anything is wrong (the reference decoder then says what)."""
        try:
            struct = self._decoder.decode(data)
        except Exception:  # ValidationError, DecodeError, and e.g. UnicodeDecodeError from a bad tag
            return None
        message = object.__new__(self._class_of[type(struct)])
        self._fill(message, struct)
        try:
            message._check()
        except MessageError:
            return None
        return message

    def _fill(self, message: Any, struct: msgspec.Struct) -> None:
        """Set each field of `message` from the validated `struct`, without the per-field checks."""
        for name in self._names[type(struct)]:
            object.__setattr__(message, name, getattr(struct, name))
