"""Local NED metres and WGS84 degrees, for the CAMARA APIs that speak latitude and longitude (the
operator's predictions and bookings) about a world that dynqos flies in metres. Written once: the
emulated operator and the edge's planner must put a point in the same place."""

from __future__ import annotations

import math
from dataclasses import dataclass

EARTH_RADIUS_M = 6_378_137.0


@dataclass(frozen=True, slots=True)
class Geo:
    """Equirectangular about an origin (x north, y east): exact enough over a few kilometres."""

    lat0: float
    lon0: float

    def to_latlon(self, x_m: float, y_m: float) -> tuple[float, float]:
        lat = self.lat0 + math.degrees(x_m / EARTH_RADIUS_M)
        lon = self.lon0 + math.degrees(y_m / (EARTH_RADIUS_M * math.cos(math.radians(self.lat0))))
        return lat, lon

    def to_local(self, lat: float, lon: float) -> tuple[float, float]:
        x = math.radians(lat - self.lat0) * EARTH_RADIUS_M
        y = math.radians(lon - self.lon0) * EARTH_RADIUS_M * math.cos(math.radians(self.lat0))
        return x, y
