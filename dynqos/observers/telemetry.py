"""dynqos messages as Foxglove channels: what `dynqos view` streams and `dynqos record` writes
(docs/observability.md).

Pure: each dynqos message in, a list of (topic, message) out, where a message is one of Foxglove's
well-known schemas (poses, scene entities, compressed images, image annotations, logs) or a JSON
object for dynqos's own (status, detections, grants, decisions) whose JSON schema is in
`JSON_SCHEMAS`. The caller stamps everything with one time base (`now_ns`, wall-clock nanoseconds) so
that a viewer on another machine and the recording agree; the drones' own stamps are their monotonic
clocks and stay in the JSON.

Frames: dynqos flies in local NED (x north, y east, z down); the scene is published in frame `ned`,
placed under a z-up frame `world` by a 180-degree turn about x (`/tf`), so that the 3D panel shows the
floor below the drone.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

from foxglove import messages as fm

from dynqos.common.messages import (
    CameraFrame,
    Detections,
    Message,
    QosDecision,
    QosGrant,
    Reference,
    State,
    SupervisorStatus,
)
from dynqos.sim.vehicle.world import World

Out = tuple[str, Any]  # (topic, a foxglove message or a JSON object)

NED = "ned"
WORLD = "world"
RISK_COLORS = {"LR": (0.2, 0.8, 0.3), "MR": (1.0, 0.65, 0.0), "HR": (0.9, 0.15, 0.1)}
RISK_ZONE_RADIUS_M = 1.0
REFERENCE_POINTS = 60  # the reference path drawn: at most this many of the horizon's samples

_STATUS_FIELDS = {
    "seq": "integer",
    "stamp_ns": "integer",
    "state": "string",
    "prev_state": "string",
    "cause": "string",
    "flow": "string",
    "camera_flow": "string",
    "control_source": "string",
    "latency": "string",
    "risk": "string",
    "qos_grant": "string",
    "camera_rate_factor": "number",
    "p_lat": "number",
    "p_cam": "number",
    "p_cc": "number",
    "rtt_ms": "number",
    "camera_latency_ms": "number",
    "spaciousness_m": "number",
    "setpoint_gap_ms": "number",
    "fallbacks": "integer",
    "watchdog": "boolean",
    "fc_text": "string",
    "fc_severity": "integer",
}


def _object(title: str, fields: dict[str, str | dict[str, Any]]) -> dict[str, Any]:
    props = {k: v if isinstance(v, dict) else {"type": [v, "null"]} for k, v in fields.items()}
    return {"title": title, "type": "object", "properties": props}


_NUMBERS = {"type": "array", "items": {"type": ["number", "null"]}}
JSON_SCHEMAS: dict[str, dict[str, Any]] = {
    "status": _object("dynqos.SupervisorStatus", dict(_STATUS_FIELDS)),
    "detections": _object(
        "dynqos.Detections",
        {
            "frame_seq": "integer",
            "stamp_ns": "integer",
            "circles_px": {"type": "array", "items": _NUMBERS},
            "centers_m": {"type": "array", "items": {"type": ["array", "null"], "items": {"type": "number"}}},
        },
    ),
    "qos/grant": _object(
        "dynqos.QosGrant",
        {"grant": "string", "backend": "string", "session_id": "string", "reason": "string"},
    ),
    "qos/decision": _object(
        "dynqos.QosDecision",
        {
            "action": "string",
            "reason": "string",
            "risk": "string",
            "latency_excess": "number",
            "holders": {"type": "array", "items": {"type": "string"}},
        },
    ),
}


def json_schema_for(topic: str) -> dict[str, Any] | None:
    """The JSON schema of a dynqos topic (`/uav1/status` -> the status schema), None for typed ones."""
    suffix = topic.split("/", 2)[-1] if topic.count("/") >= 2 else ""
    return JSON_SCHEMAS.get(suffix)


def stamp(ns: int) -> fm.Timestamp:
    return fm.Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


def _color(rgb: tuple[float, float, float], alpha: float = 1.0) -> fm.Color:
    return fm.Color(r=rgb[0], g=rgb[1], b=rgb[2], a=alpha)


def _rgb255(color: tuple[int, int, int], alpha: float = 1.0) -> fm.Color:
    return fm.Color(r=color[0] / 255, g=color[1] / 255, b=color[2] / 255, a=alpha)


def _pose(pos: Iterable[float], quat_wxyz: Iterable[float] = (1.0, 0.0, 0.0, 0.0)) -> fm.Pose:
    x, y, z = (float(v) for v in pos)
    w, qx, qy, qz = (float(v) for v in quat_wxyz)
    return fm.Pose(position=fm.Vector3(x=x, y=y, z=z), orientation=fm.Quaternion(x=qx, y=qy, z=qz, w=w))


def frames(now_ns: int) -> Out:
    """`world` (z up) to `ned`: half a turn about x."""
    transform = fm.FrameTransform(
        timestamp=stamp(now_ns),
        parent_frame_id=WORLD,
        child_frame_id=NED,
        translation=fm.Vector3(x=0.0, y=0.0, z=0.0),
        rotation=fm.Quaternion(x=1.0, y=0.0, z=0.0, w=0.0),
    )
    return "/tf", fm.FrameTransforms(transforms=[transform])


def world_scene(world: World, now_ns: int) -> Out:
    """The world's obstacles: pillars as cylinders, boxes as cubes, hoops as line loops."""
    entities = []
    for i, c in enumerate(world.cylinders):
        height = abs(c.z_bottom_m - c.z_top_m)
        center = (c.center_m[0], c.center_m[1], (c.z_top_m + c.z_bottom_m) / 2)
        size = fm.Vector3(x=2 * c.radius_m, y=2 * c.radius_m, z=height)
        cylinder = fm.CylinderPrimitive(
            pose=_pose(center), size=size, bottom_scale=1.0, top_scale=1.0, color=_rgb255(c.color)
        )
        entities.append(_entity(f"cylinder/{i}", now_ns, cylinders=[cylinder]))
    for i, b in enumerate(world.boxes):
        middle = [(lo + hi) / 2 for lo, hi in zip(b.min_m, b.max_m, strict=True)]
        size = fm.Vector3(
            x=b.max_m[0] - b.min_m[0], y=b.max_m[1] - b.min_m[1], z=abs(b.max_m[2] - b.min_m[2])
        )
        cube = fm.CubePrimitive(pose=_pose(middle), size=size, color=_rgb255(b.color))
        entities.append(_entity(f"box/{i}", now_ns, cubes=[cube]))
    for i, h in enumerate(world.hoops):
        entities.append(_entity(f"hoop/{i}", now_ns, lines=[_ring(h.center_m, h.normal, h.radius_m)]))
    return "/world", fm.SceneUpdate(entities=entities)


def _ring(center: Iterable[float], normal: Iterable[float], radius: float) -> fm.LinePrimitive:
    cx, cy, cz = center
    nx, ny, nz = normal
    norm = math.sqrt(nx * nx + ny * ny + nz * nz) or 1.0
    n = (nx / norm, ny / norm, nz / norm)
    a = (-n[1], n[0], 0.0) if abs(n[2]) < 0.9 else (1.0, 0.0, 0.0)  # a vector across the normal
    la = math.sqrt(sum(v * v for v in a))
    u = tuple(v / la for v in a)
    v = (n[1] * u[2] - n[2] * u[1], n[2] * u[0] - n[0] * u[2], n[0] * u[1] - n[1] * u[0])
    points = [
        fm.Point3(
            x=cx + radius * (math.cos(t) * u[0] + math.sin(t) * v[0]),
            y=cy + radius * (math.cos(t) * u[1] + math.sin(t) * v[1]),
            z=cz + radius * (math.cos(t) * u[2] + math.sin(t) * v[2]),
        )
        for t in (2 * math.pi * k / 32 for k in range(32))
    ]
    return fm.LinePrimitive(
        type=fm.LinePrimitiveLineType.LineLoop,
        pose=_pose((0, 0, 0)),
        thickness=0.05,
        points=points,
        color=_color((1.0, 0.55, 0.08)),
    )


def _entity(entity_id: str, now_ns: int, **primitives: Any) -> fm.SceneEntity:
    return fm.SceneEntity(timestamp=stamp(now_ns), frame_id=NED, id=entity_id, **primitives)


@dataclass
class DroneView:
    """What is known of one drone between messages (the scene is drawn from its latest pose)."""

    pose: State | None = None
    status: SupervisorStatus | None = None


@dataclass
class Telemetry:
    """Turns each received dynqos message into the channels it feeds."""

    drones: dict[str, DroneView] = field(default_factory=dict)

    def convert(self, message: Message, now_ns: int) -> list[Out]:
        view = self.drones.setdefault(message.uav, DroneView())
        uav = message.uav
        if isinstance(message, State):
            view.pose = message
            pose = fm.PoseInFrame(
                timestamp=stamp(now_ns), frame_id=NED, pose=_pose(message.pos_m, message.quat)
            )
            return [(f"/{uav}/pose", pose)]
        if isinstance(message, SupervisorStatus):
            return self._status(view, message, now_ns)
        if isinstance(message, CameraFrame):
            return self._image(message, now_ns)
        if isinstance(message, Detections):
            return self._detections(message, now_ns)
        if isinstance(message, Reference):
            return [(f"/{uav}/scene", fm.SceneUpdate(entities=[_reference_path(message, now_ns)]))]
        if isinstance(message, QosGrant):
            grant = {
                "grant": message.grant.value,
                "backend": message.backend,
                "session_id": message.session_id,
                "reason": message.reason,
            }
            return [(f"/{uav}/qos/grant", grant)]
        if isinstance(message, QosDecision):
            decision = {
                "action": message.action,
                "reason": message.reason,
                "risk": message.risk,
                "latency_excess": message.latency_excess,
                "holders": list(message.holders),
            }
            log = fm.Log(
                timestamp=stamp(now_ns),
                level=fm.LogLevel.Info,
                name=uav,
                message=f"{uav}: arbiter {message.action}: {message.reason}",
            )
            return [(f"/{uav}/qos/decision", decision), ("/log", log)]
        return []

    def _status(self, view: DroneView, s: SupervisorStatus, now_ns: int) -> list[Out]:
        previous = view.status
        view.status = s
        out: list[Out] = [(f"/{s.uav}/status", status_json(s))]
        if view.pose is not None:
            color = _color(RISK_COLORS.get(s.risk, (0.6, 0.6, 0.6)), 0.25)
            size = fm.Vector3(x=2 * RISK_ZONE_RADIUS_M, y=2 * RISK_ZONE_RADIUS_M, z=2 * RISK_ZONE_RADIUS_M)
            body = fm.CubePrimitive(
                pose=_pose(view.pose.pos_m, view.pose.quat),
                size=fm.Vector3(x=0.45, y=0.45, z=0.12),
                color=_color((0.15, 0.15, 0.2)),
            )
            zone = fm.SpherePrimitive(pose=_pose(view.pose.pos_m), size=size, color=color)
            label = fm.TextPrimitive(
                pose=_pose((view.pose.pos_m[0], view.pose.pos_m[1], view.pose.pos_m[2] - 0.5)),
                billboard=True,
                font_size=14.0,
                scale_invariant=True,
                color=_color((1, 1, 1)),
                text=f"{s.uav} {s.state.value} {s.risk} {s.flow.value}",
            )
            entities = [
                _entity(f"{s.uav}/body", now_ns, cubes=[body], texts=[label]),
                _entity(f"{s.uav}/risk", now_ns, spheres=[zone]),
            ]
            out.append((f"/{s.uav}/scene", fm.SceneUpdate(entities=entities)))
        if previous is not None and s.state != previous.state:
            level = fm.LogLevel.Warning if s.state.value == "qA" else fm.LogLevel.Info
            text = f"{s.uav}: {previous.state.value} -> {s.state.value} ({s.cause or 'no cause given'})"
            out.append(("/log", fm.Log(timestamp=stamp(now_ns), level=level, name=s.uav, message=text)))
        return out

    def _image(self, frame: CameraFrame, now_ns: int) -> list[Out]:
        if frame.kind != "rgb" or frame.encoding != "jpeg":
            return []
        image = fm.CompressedImage(
            timestamp=stamp(now_ns), frame_id=f"{frame.uav}/camera", data=frame.payload, format="jpeg"
        )
        return [(f"/{frame.uav}/camera/rgb", image)]

    def _detections(self, d: Detections, now_ns: int) -> list[Out]:
        circles = [
            fm.CircleAnnotation(
                timestamp=stamp(now_ns),
                position=fm.Point2(x=u, y=v),
                diameter=2 * r,
                thickness=3.0,
                outline_color=_color((0.1, 1.0, 0.3)),
                fill_color=_color((0, 0, 0), 0.0),
            )
            for u, v, r in d.circles_px
        ]
        as_json = {
            "frame_seq": d.frame_seq,
            "stamp_ns": d.stamp_ns,
            "circles_px": [list(c) for c in d.circles_px],
            "centers_m": [list(c) if c is not None else None for c in d.centers_m],
        }
        return [
            (f"/{d.uav}/detections", as_json),
            (f"/{d.uav}/camera/annotations", fm.ImageAnnotations(timestamp=stamp(now_ns), circles=circles)),
        ]


def _reference_path(ref: Reference, now_ns: int) -> fm.SceneEntity:
    step = max(1, len(ref.pos_m) // REFERENCE_POINTS)
    points = [fm.Point3(x=p[0], y=p[1], z=p[2]) for p in ref.pos_m[::step]]
    line = fm.LinePrimitive(
        type=fm.LinePrimitiveLineType.LineStrip,
        pose=_pose((0, 0, 0)),
        thickness=0.03,
        points=points,
        color=_color((0.2, 0.6, 1.0)),
    )
    return _entity(f"{ref.uav}/reference", now_ns, lines=[line])


def status_json(s: SupervisorStatus) -> dict[str, Any]:
    values = {name: getattr(s, name) for name in _STATUS_FIELDS}
    return {k: (v.value if hasattr(v, "value") else v) for k, v in values.items()}
