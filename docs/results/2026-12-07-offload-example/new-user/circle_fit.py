"""Face the centre of the circle the drone is flying, fitted at the edge from its recent track."""

from collections import deque

import msgspec
import numpy as np

from dynqos.offload import Drone, Edge, Onboard, Steer, Task


class Track(msgspec.Struct):
    xy_m: np.ndarray  # the last positions, north and east, one row each


class Circle(msgspec.Struct):
    center_m: tuple[float, float]
    radius_m: float


TASK = Task("circle-fit", request=Track, answer=Circle, rate_hz=5, deadline_s=0.1, flow="control")


def fit(track: Track) -> Circle:
    """Least squares: x^2 + y^2 = 2ax + 2by + c, centre (a, b), radius sqrt(c + a^2 + b^2)."""
    x, y = track.xy_m[:, 0], track.xy_m[:, 1]
    a, b, c = np.linalg.lstsq(np.column_stack([2 * x, 2 * y, np.ones_like(x)]), x * x + y * y, rcond=None)[0]
    return Circle((float(a), float(b)), float(np.sqrt(max(c + a * a + b * b, 0.0))))


seen: deque[tuple[float, float]] = deque(maxlen=50)


def ask(drone: Drone) -> Track | None:
    seen.append(drone.pos_m[:2])
    return Track(np.array(seen)) if drone.flying and len(seen) >= 10 else None


def face(circle: Circle, drone: Drone) -> Steer:
    north, east = circle.center_m[0] - drone.pos_m[0], circle.center_m[1] - drone.pos_m[1]
    return Steer(yaw_rad=float(np.arctan2(east, north)))


def keep(drone: Drone) -> Steer:
    return Steer(yaw_rad=drone.yaw_rad)


EDGE = Edge(TASK, handle=fit)
ONBOARD = Onboard(TASK, request=ask, apply=face, fallback=keep)
