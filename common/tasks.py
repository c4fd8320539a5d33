"""A task the runtime offloads for a user, declared once as plain data that both sides import.

A `Task` says what crosses the link (its request and answer types, each with a size bound), how often
the drone asks (`rate_hz`), how late an answer may come and still be of use (`deadline_s`), and which
flow it rides: a *control* task rides the State's flow and switches with it, a *bulk* task rides the
camera's and is throttled with it. `Edge` pairs a task with the function that answers it; `Onboard`
with what the drone does: build a request, apply an answer, fly a fallback when the answer is late.

What a user writes imports only `dynqos.offload`, which re-exports the names here. The runtime enforces
the deadline with its own timer onboard, not by asking the handler (zenoh-flow's `deadline` reported a
miss only once the late work had finished), keeps the rate (ROS 2's `deadline`) apart from the budget
of one call, and sends the budget with each request so the edge can drop work already late.

Bodies are msgpack through msgspec, which checks a decoded body against the declared type; numpy arrays
travel as a msgpack extension (dtype, shape, bytes).
"""

from __future__ import annotations

import importlib
import importlib.util
import math
import struct
import sys
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, Literal, TypeVar

import msgspec
import numpy as np

from dynqos.common.errors import DynqosError, KeyExprError
from dynqos.common.keys import check_task_name
from dynqos.common.message_base import MAX_PAYLOAD_BYTES

FLOW_CLASSES = ("control", "bulk")
RATE_RANGE_HZ = (0.1, 1000.0)  # as [control] t_mpc_s allows
DEADLINE_RANGE_S = (0.001, 60.0)  # as [supervisor] watchdog_s allows
DEFAULT_MAX_BYTES = 64 * 1024
NDARRAY_EXT = 1  # the msgpack extension code of a numpy array
MAX_ARRAY_DIMS = 8

Req = TypeVar("Req")
Ans = TypeVar("Ans")


class TaskError(DynqosError):
    """A task declared wrongly, or one that cannot be loaded: one line, naming the task or the target."""


class PayloadError(DynqosError):
    """A request or answer body that does not fit its task's type or size bound."""


@dataclass(frozen=True, slots=True)
class Task(Generic[Req, Ans]):
    """What is offloaded. `request` and `answer` are types msgspec can check: a msgspec Struct, a
    dataclass, a TypedDict, or plain `dict`, `list`, `float`, ...; a field may be an `np.ndarray`."""

    name: str
    request: type[Req]
    answer: type[Ans]
    rate_hz: float
    deadline_s: float
    flow: Literal["control", "bulk"] = "control"
    max_request_bytes: int = DEFAULT_MAX_BYTES
    max_answer_bytes: int = DEFAULT_MAX_BYTES
    # Whether any replica may answer any request (no state kept between calls): then replicas of its
    # edge service share the drones and take over each other's at once.
    stateless: bool = True

    def __post_init__(self) -> None:
        try:
            check_task_name(self.name)
        except KeyExprError as exc:
            raise TaskError(str(exc)) from None
        _require(self, self.flow in FLOW_CLASSES, f"flow must be one of {FLOW_CLASSES}, got {self.flow!r}")
        low, high = RATE_RANGE_HZ
        _require(
            self, _number(self.rate_hz) and low <= self.rate_hz <= high, f"rate_hz must be {low}..{high}"
        )
        low, high = DEADLINE_RANGE_S
        ok = _number(self.deadline_s) and low <= self.deadline_s <= high
        _require(self, ok, f"deadline_s must be {low}..{high} s")
        for name in ("max_request_bytes", "max_answer_bytes"):
            size = getattr(self, name)
            ok = isinstance(size, int) and 16 <= size <= MAX_PAYLOAD_BYTES
            _require(self, ok, f"{name} must be 16..{MAX_PAYLOAD_BYTES}")
        for name in ("request", "answer"):
            try:
                msgspec.msgpack.Decoder(getattr(self, name), dec_hook=_dec_hook)
            except (TypeError, ValueError) as exc:
                raise TaskError(
                    f"task {self.name}: {name} type is not one msgspec can check: {exc}"
                ) from None

    @property
    def period_ns(self) -> int:
        return round(1e9 / self.rate_hz)

    @property
    def deadline_ns(self) -> int:
        return round(self.deadline_s * 1e9)


@dataclass(frozen=True, slots=True)
class Drone:
    """What a task's onboard side sees of the drone at a call: local NED, the drone's own clock."""

    uav: str
    now_s: float
    pos_m: tuple[float, float, float]
    vel_mps: tuple[float, float, float]
    yaw_rad: float
    flying: bool  # offboard, offloading; False on the ground and in the climb


@dataclass(frozen=True, slots=True)
class Steer:
    """What a task's onboard side does to the flight: the heading the drone flies (None: leave it)."""

    yaw_rad: float | None = None

    def __post_init__(self) -> None:
        if self.yaw_rad is not None and not _number(self.yaw_rad):
            raise PayloadError(f"Steer.yaw_rad must be a finite number, got {self.yaw_rad!r}")


@dataclass(frozen=True, slots=True)
class Edge(Generic[Req, Ans]):
    """A task's edge side: `handle` answers one request (it runs on the service's worker thread)."""

    task: Task[Req, Ans]
    handle: Callable[[Req], Ans]

    def __post_init__(self) -> None:
        _check_task(self.task, "Edge")
        _require(self.task, callable(self.handle), "Edge.handle must be callable")


@dataclass(frozen=True, slots=True)
class Onboard(Generic[Req, Ans]):
    """A task's onboard side: `request` builds the call (None: skip this one), `apply` turns an answer in
    time into a Steer, `fallback` is flown while answers are late or absent. Each should return within
    a few milliseconds: they run on the task's own thread, not the control loop's."""

    task: Task[Req, Ans]
    request: Callable[[Drone], Req | None]
    apply: Callable[[Ans, Drone], Steer | None]
    fallback: Callable[[Drone], Steer | None]

    def __post_init__(self) -> None:
        _check_task(self.task, "Onboard")
        for name in ("request", "apply", "fallback"):
            _require(self.task, callable(getattr(self, name)), f"Onboard.{name} must be callable")


@dataclass(frozen=True, slots=True)
class Service(Generic[Req, Ans]):
    """A task's edge side as a core on the edge runtime, for work one function per call cannot do: state
    kept between calls (the MPC's warm starts, per drone), time of its own (replicas' leases, the
    detector's frames joined from their parts), or a wire of its own. `make(config, ports, replica)`
    builds the core (an `EdgeCore`, edge/runtime.py), which declares its subscriptions and publishers
    on `ports.bus`; `replica` is `--replica-id` ("": the core's own default). `name` is the process's
    name in logs, health, metrics and its identity (default task-<name>); `metrics(core, process)`
    registers its Prometheus families. The MPC and the detector are served this way."""

    task: Task[Req, Ans]
    make: Callable[[Any, Any, str], Any]
    name: str = ""
    metrics: Callable[[Any, Any], None] | None = None

    def __post_init__(self) -> None:
        _check_task(self.task, "Service")
        _require(self.task, callable(self.make), "Service.make must be callable")
        ok = self.metrics is None or callable(self.metrics)
        _require(self.task, ok, "Service.metrics must be callable")
        if self.name:
            try:
                check_task_name(self.name)
            except KeyExprError as exc:
                raise TaskError(f"task {self.task.name}: Service.name: {exc}") from None

    @property
    def service_name(self) -> str:
        return self.name or f"task-{self.task.name}"


class Codec(Generic[Req, Ans]):
    """A task's bodies to and from bytes, each checked against its type and its size bound."""

    def __init__(self, task: Task[Req, Ans]) -> None:
        self.task = task
        self._encoder = msgspec.msgpack.Encoder(enc_hook=_enc_hook)
        self._requests = msgspec.msgpack.Decoder(task.request, dec_hook=_dec_hook, ext_hook=_ext_hook)
        self._answers = msgspec.msgpack.Decoder(task.answer, dec_hook=_dec_hook, ext_hook=_ext_hook)

    def encode_request(self, request: Req) -> bytes:
        return self._encode(request, self._requests, self.task.max_request_bytes, "request")

    def encode_answer(self, answer: Ans) -> bytes:
        return self._encode(answer, self._answers, self.task.max_answer_bytes, "answer")

    def decode_request(self, body: bytes) -> Req:
        request: Req = self._decode(self._requests, body, self.task.max_request_bytes, "request")
        return request

    def decode_answer(self, body: bytes) -> Ans:
        answer: Ans = self._decode(self._answers, body, self.task.max_answer_bytes, "answer")
        return answer

    def _encode(self, value: Any, decoder: msgspec.msgpack.Decoder[Any], limit: int, what: str) -> bytes:
        """The bytes of `value`, decoded once more against the declared type: what the other side will
        refuse is refused here, where the mistake is made (a dataclass holding a str for a float)."""
        try:
            data = self._encoder.encode(value)
        except (TypeError, ValueError, OverflowError) as exc:
            raise PayloadError(f"{what} does not encode: {_short(exc)}") from None
        self._decode(decoder, data, limit, what)
        return data

    def _decode(self, decoder: msgspec.msgpack.Decoder[Any], body: bytes, limit: int, what: str) -> Any:
        if len(body) > limit:
            raise PayloadError(f"{what} is {len(body)} bytes, over the task's {limit}")
        try:
            return decoder.decode(body)
        except (msgspec.DecodeError, TypeError, ValueError) as exc:
            raise PayloadError(f"{what} is not a {_type_name(decoder.type)}: {_short(exc)}") from None


def load(target: str, kind: type[Any] | tuple[type[Any], ...]) -> Any:
    """The object `target` names, "module:ATTR" or "path/file.py:ATTR", checked to be a `kind`. Raises
    TaskError in one line (a module that fails to import, a missing name, the wrong kind), never the
    user's traceback."""
    module_name, sep, attr = target.rpartition(":")
    if not sep or not module_name or not attr:
        raise TaskError(f"{target!r}: name a task as MODULE:ATTR or path/to/file.py:ATTR")
    try:
        module = _import(module_name)
    except TaskError:
        raise
    except BaseException as exc:  # the user's module may raise anything, SystemExit included
        raise TaskError(
            f"{target}: its module failed to import: {type(exc).__name__}: {_short(exc)}"
        ) from None
    found = getattr(module, attr, None)
    if not isinstance(found, kind):
        what = "nothing" if found is None else f"a {type(found).__name__}"
        kinds = " or ".join(
            f"dynqos.offload.{k.__name__}" for k in (kind if isinstance(kind, tuple) else [kind])
        )
        raise TaskError(f"{target}: {attr} is {what}, not a {kinds}")
    return found


def _import(name: str) -> Any:
    if name.endswith(".py"):
        path = Path(name)
        if not path.is_file():
            raise TaskError(f"{name}: no such file")
        unique = f"dynqos_task_{path.stem}_{zlib.crc32(str(path.resolve()).encode()):08x}"
        if unique in sys.modules:
            return sys.modules[unique]
        spec = importlib.util.spec_from_file_location(unique, path)
        if spec is None or spec.loader is None:
            raise TaskError(f"{name}: not a Python module")
        module = importlib.util.module_from_spec(spec)
        sys.modules[unique] = module  # dataclasses look their module up while the file runs
        try:
            spec.loader.exec_module(module)
        except BaseException:
            del sys.modules[unique]
            raise
        return module
    if "" not in sys.path and str(Path.cwd()) not in sys.path:
        sys.path.insert(0, str(Path.cwd()))  # as `python -m`: a module beside the user's files
    return importlib.import_module(name)


def _enc_hook(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        if value.dtype.hasobject or value.ndim > MAX_ARRAY_DIMS:
            raise TypeError(f"an array of {value.dtype} in {value.ndim} dimensions cannot travel")
        dtype = value.dtype.str.encode()
        header = struct.pack(f"<B{len(dtype)}sB{value.ndim}Q", len(dtype), dtype, value.ndim, *value.shape)
        return msgspec.msgpack.Ext(NDARRAY_EXT, header + np.ascontiguousarray(value).tobytes())
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"{type(value).__name__} cannot travel in a task's body")


def _ext_hook(code: int, data: memoryview) -> Any:
    """An array from its extension: the dtype's length and string, the dimensions, each size, the bytes."""
    if code != NDARRAY_EXT:
        raise ValueError(f"unknown msgpack extension {code}")
    raw = bytes(data)
    try:
        size = raw[0]
        dtype = np.dtype(raw[1 : 1 + size].decode())
        ndim = raw[1 + size]
        start = 2 + size + 8 * ndim
        shape = struct.unpack_from(f"<{ndim}Q", raw, 2 + size)
    except (IndexError, struct.error, TypeError, ValueError, UnicodeDecodeError) as exc:
        raise ValueError(f"array header does not decode: {exc}") from None
    if dtype.hasobject or ndim > MAX_ARRAY_DIMS:
        raise ValueError(f"array of {dtype} in {ndim} dimensions refused")
    if len(raw) - start != dtype.itemsize * math.prod(shape):
        raise ValueError(f"array of {dtype} {shape} with {len(raw) - start} bytes")
    return np.frombuffer(raw, dtype=dtype, offset=start).reshape(shape)


def _dec_hook(kind: type, value: Any) -> Any:
    if kind is np.ndarray:
        if isinstance(value, np.ndarray):
            return value
        try:
            return np.asarray(value, dtype=float)
        except (TypeError, ValueError) as exc:
            raise msgspec.ValidationError(f"expected an array: {exc}") from None
    raise NotImplementedError(f"{kind} is not a type a task's body can hold")


def _check_task(task: object, what: str) -> None:
    if not isinstance(task, Task):
        raise TaskError(f"{what}: its task must be a dynqos.offload.Task, got {type(task).__name__}")


def _require(task: Task[Any, Any], ok: bool, reason: str) -> None:
    if not ok:
        raise TaskError(f"task {task.name}: {reason}")


def _number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _type_name(kind: object) -> str:
    return getattr(kind, "__name__", str(kind))


def _short(exc: BaseException) -> str:
    return str(exc).replace("\n", " ")[:200]
