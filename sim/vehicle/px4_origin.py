"""Several PX4 instances in one local frame: each boots where its drone stands (its SIH home shifted by
the drone's start, north and east, from the fleet's common origin), and is then told the common origin as
its estimator's (SET_GPS_GLOBAL_ORIGIN, as a ground station tells a vehicle flying indoors), so that its
LOCAL_POSITION_NED is the fleet's frame: where the planner sends it, where the camera renders it from
and where the radio map places it. Without that, every instance reports (0, 0) where it boots.

The origin goes out on the instance's offboard link from the port PX4 sends that link to (14540+N), so
PX4 keeps sending there and the onboard daemon, which listens there later, hears it as before."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from dynqos.common import mavsign
from dynqos.common.errors import DynqosError
from dynqos.common.geo import EARTH_RADIUS_M

log = logging.getLogger(__name__)

DEFAULT_HOME = (47.397742, 8.545594, 489.4)  # PX4 SITL's default home (its start-up scripts')
ORIGIN_TOLERANCE_M = 1.0  # SIH's home is a float32 parameter: ~0.4 m steps in latitude


@dataclass(frozen=True, slots=True)
class Home:
    """Where a PX4 SITL instance boots, in degrees and metres above sea level."""

    lat_deg: float
    lon_deg: float
    alt_m: float

    @classmethod
    def of(cls, env: Mapping[str, str]) -> Home:
        """PX4_HOME_LAT / LON / ALT from the environment, else PX4's default."""
        lat, lon, alt = DEFAULT_HOME
        try:
            return cls(
                float(env.get("PX4_HOME_LAT", lat)),
                float(env.get("PX4_HOME_LON", lon)),
                float(env.get("PX4_HOME_ALT", alt)),
            )
        except ValueError:
            raise DynqosError("PX4_HOME_LAT, PX4_HOME_LON and PX4_HOME_ALT must be numbers") from None

    def shifted(self, north_east_m: tuple[float, float]) -> Home:
        north, east = north_east_m
        lat = self.lat_deg + math.degrees(north / EARTH_RADIUS_M)
        lon = self.lon_deg + math.degrees(east / (EARTH_RADIUS_M * math.cos(math.radians(self.lat_deg))))
        return Home(lat, lon, self.alt_m)

    def environment(self) -> dict[str, str]:
        return {
            "PX4_HOME_LAT": f"{self.lat_deg:.9f}",
            "PX4_HOME_LON": f"{self.lon_deg:.9f}",
            "PX4_HOME_ALT": f"{self.alt_m:.3f}",
        }


def set_origin(
    ports: Any, origin: Home, start_m: tuple[float, float], key: bytes | None, timeout_s: float
) -> None:
    """Tell PX4 instance `ports.instance` the common origin, and wait until its local position is its
    start (within ORIGIN_TOLERANCE_M)."""
    conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{ports.offboard_remote}", source_system=245)
    conn.mav = mavlink.MAVLink(conn, srcSystem=245, srcComponent=mavlink.MAV_COMP_ID_MISSIONPLANNER)
    conn.mav.robust_parsing = True
    if key is not None:
        conn.setup_signing(key, sign_outgoing=True, initial_timestamp=mavsign.timestamp_now(), link_id=9)
    try:
        _until_at_start(conn, ports, origin, start_m, timeout_s)
    finally:
        conn.close()


def _until_at_start(
    conn: Any, ports: Any, origin: Home, start_m: tuple[float, float], timeout_s: float
) -> None:
    deadline = time.monotonic() + timeout_s
    next_send = 0.0
    where = None
    while time.monotonic() < deadline:
        msg = conn.recv_match(type="LOCAL_POSITION_NED", blocking=True, timeout=0.2)
        if msg is not None and msg.get_srcSystem() == ports.system_id:
            where = (msg.x, msg.y)
            if math.dist(where, start_m) <= ORIGIN_TOLERANCE_M:
                log.info("px4: instance %d is at (%.2f, %.2f) m in the fleet's frame", ports.instance, *where)
                return
        if time.monotonic() >= next_send and msg is not None:  # PX4 has spoken: we can answer it
            next_send = time.monotonic() + 1.0
            conn.mav.set_gps_global_origin_send(
                ports.system_id,
                round(origin.lat_deg * 1e7),
                round(origin.lon_deg * 1e7),
                round(origin.alt_m * 1000),
                0,
            )
    raise DynqosError(
        f"PX4 instance {ports.instance} did not take the fleet's origin in {timeout_s:g} s: "
        f"at {where} m, not {start_m} m"
    )
