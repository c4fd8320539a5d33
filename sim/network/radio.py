"""Radio conditions that depend on where the drone is: a radio map and link adaptation, as pure logic.

The emulated cell used to give every drone the same radio wherever it flew. A real drone's uplink
rate follows its SINR: it drops behind a building, in a coverage hole, and as the drone climbs and
sees more neighbouring cells (3GPP TR 36.777). The map here is a generator, not a survey: RSRP from
each site by log-distance path loss, a fixed loss when the straight line to the site passes through an
obstacle of the world, coverage holes with a soft edge; the SINR is the best site's RSRP over noise
and interference that rises with height. Link adaptation maps the SINR to a CQI of 3GPP TS 38.214's
table 1 and its spectral efficiency; a drone's rate factor is that efficiency over the one at the
reference SINR, where the cell carries its nominal capacity (docs/radio.md).
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

from dynqos.common.config.radio import CoverageHoleConfig, RadioConfig, RadioSiteConfig
from dynqos.sim.vehicle.world import Box, Cylinder, World

# TS 38.214 Table 5.2.2.1-2 (4-bit CQI table 1): spectral efficiency (bits per resource element) of CQI 1-15.
CQI_EFFICIENCY = (
    0.1523,
    0.2344,
    0.3770,
    0.6016,
    0.8770,
    1.1758,
    1.4766,
    1.9141,
    2.4063,
    2.7305,
    3.3223,
    3.9023,
    4.5234,
    5.1152,
    5.5547,
)
# TR 36.942 Annex A.2: link-level throughput as an attenuated Shannon bound, alpha * log2(1 + SINR).
SHANNON_ALPHA = 0.6
SPEED_OF_LIGHT_MPS = 299_792_458.0


def cqi_threshold_db(efficiency: float) -> float:
    """The SINR at which the attenuated Shannon bound reaches `efficiency`: where that CQI is chosen."""
    return 10 * math.log10(2 ** (efficiency / SHANNON_ALPHA) - 1)


CQI_THRESHOLDS_DB = tuple(cqi_threshold_db(e) for e in CQI_EFFICIENCY)  # -7.2 dB (CQI 1) .. 27.9 dB (15)


def cqi(sinr_db: float) -> int:
    """The highest CQI whose threshold the SINR reaches; 0 is out of range (no transmission)."""
    return bisect.bisect_right(CQI_THRESHOLDS_DB, sinr_db)


def efficiency(sinr_db: float) -> float:
    """Bits per resource element at this SINR (0 out of range)."""
    index = cqi(sinr_db)
    return CQI_EFFICIENCY[index - 1] if index else 0.0


@dataclass(frozen=True, slots=True)
class Radio:
    """What a modem at one position reports, and the rate it gets there."""

    rsrp_dbm: float
    sinr_db: float
    cqi: int
    rate_factor: float  # the drone's share of resources carries this times the cell's nominal bits
    site: str  # the serving site (the strongest)


class RadioMap:
    """The radio over the world, for any position (x, y, z in NED metres; the ground at z = 0)."""

    def __init__(self, config: RadioConfig, world: World | None = None) -> None:
        self.config = config
        self.obstacles: tuple[Box | Cylinder, ...] = (*world.boxes, *world.cylinders) if world else ()
        wavelength_m = SPEED_OF_LIGHT_MPS / (config.carrier_ghz * 1e9)
        self.loss_at_1m_db = 20 * math.log10(4 * math.pi / wavelength_m)  # free space at 1 m
        self.reference_efficiency = efficiency(config.reference_sinr_db)

    def path_loss_db(self, site: RadioSiteConfig, pos_m: tuple[float, float, float]) -> float:
        distance = max(1.0, math.dist(site.position_m, pos_m))
        loss = self.loss_at_1m_db + 10 * self.config.path_loss_exponent * math.log10(distance)
        if any(_blocks(o, site.position_m, pos_m) for o in self.obstacles):
            loss += self.config.obstacle_loss_db
        return loss + sum(_hole_loss_db(h, pos_m) for h in self.config.holes)

    def at(self, pos_m: tuple[float, float, float]) -> Radio:
        best = max(self.config.sites, key=lambda s: s.tx_dbm_per_re - self.path_loss_db(s, pos_m))
        rsrp = best.tx_dbm_per_re - self.path_loss_db(best, pos_m)
        height_m = max(0.0, -pos_m[2])
        interference = self.config.interference_dbm + self.config.interference_db_per_m * height_m
        sinr = rsrp - interference
        factor = efficiency(sinr) / self.reference_efficiency if self.reference_efficiency else 0.0
        return Radio(rsrp_dbm=rsrp, sinr_db=sinr, cqi=cqi(sinr), rate_factor=factor, site=best.name)


def _hole_loss_db(hole: CoverageHoleConfig, pos_m: tuple[float, float, float]) -> float:
    if -pos_m[2] > hole.top_m:
        return 0.0
    off = math.hypot(pos_m[0] - hole.center_m[0], pos_m[1] - hole.center_m[1]) - hole.radius_m
    if off <= 0:
        return hole.loss_db
    if off >= hole.edge_m:
        return 0.0
    return hole.loss_db * (1 - off / hole.edge_m)


def _blocks(obstacle: Box | Cylinder, a: tuple[float, float, float], b: tuple[float, float, float]) -> bool:
    """Does the segment a-b pass through the obstacle? (an end inside it counts: the antenna is shadowed)"""
    if isinstance(obstacle, Box):
        return _segment_hits_box(obstacle.min_m, obstacle.max_m, a, b)
    return _segment_hits_cylinder(obstacle, a, b)


def _segment_hits_box(
    lo: tuple[float, float, float],
    hi: tuple[float, float, float],
    a: tuple[float, float, float],
    b: tuple[float, float, float],
) -> bool:
    """The slab method: the segment's parameter range inside every axis's slab is not empty."""
    t0, t1 = 0.0, 1.0
    for axis in range(3):
        d = b[axis] - a[axis]
        if abs(d) < 1e-12:
            if not lo[axis] <= a[axis] <= hi[axis]:
                return False
            continue
        s0, s1 = (lo[axis] - a[axis]) / d, (hi[axis] - a[axis]) / d
        t0, t1 = max(t0, min(s0, s1)), min(t1, max(s0, s1))
        if t0 > t1:
            return False
    return True


def _segment_hits_cylinder(
    cyl: Cylinder, a: tuple[float, float, float], b: tuple[float, float, float]
) -> bool:
    """The parameter range where the segment is within the radius, cut by the range within the heights."""
    dx, dy, dz = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    ox, oy = a[0] - cyl.center_m[0], a[1] - cyl.center_m[1]
    qa, qb, qc = dx * dx + dy * dy, 2 * (ox * dx + oy * dy), ox * ox + oy * oy - cyl.radius_m**2
    if qa < 1e-12:  # vertical segment
        if qc > 0:
            return False
        t0, t1 = 0.0, 1.0
    else:
        disc = qb * qb - 4 * qa * qc
        if disc < 0:
            return False
        root = math.sqrt(disc)
        t0, t1 = max(0.0, (-qb - root) / (2 * qa)), min(1.0, (-qb + root) / (2 * qa))
        if t0 > t1:
            return False
    if abs(dz) < 1e-12:
        return cyl.z_top_m <= a[2] <= cyl.z_bottom_m
    s0, s1 = (cyl.z_top_m - a[2]) / dz, (cyl.z_bottom_m - a[2]) / dz
    return max(t0, min(s0, s1)) <= min(t1, max(s0, s1))
