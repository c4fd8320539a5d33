"""Config of the emulated cell's radio ([cell.radio]): where the drones' radio conditions come from.

Off by default: every drone then has the same radio wherever it flies (the cell's own capacity and
scheduling, docs/cell.md). On, each drone's uplink follows the SINR at its position (docs/radio.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

from dynqos.common.config.validate import In, _require, checked
from dynqos.common.keys import UAV_ID_PATTERN


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class RadioSiteConfig:
    """A base station (gNB) whose signal the drones receive: its antenna's position (NED metres, z up
    is negative) and its transmit power per resource element."""

    name: str = "site1"
    position_m: tuple[float, float, float] = (-300.0, 0.0, -25.0)
    # 46 dBm over a 40 MHz carrier at 30 kHz spacing (106 resource blocks, 1272 subcarriers): 15 dBm each
    tx_dbm_per_re: Annotated[float, In(-30, 60, "must be in -30..60 dBm")] = 15.0

    def __post_init__(self) -> None:
        _require(bool(self.name), "name", "must not be empty")


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class CoverageHoleConfig:
    """A coverage hole: `loss_db` more path loss within `radius_m` of `center_m` (x, y), fading to none
    over `edge_m` beyond it, up to `top_m` metres above the ground (above it the hole ends)."""

    center_m: tuple[float, float]
    radius_m: Annotated[float, In(0.1, 10_000, "must be in 0.1..10000 m")] = 3.0
    edge_m: Annotated[float, In(0, 1000, "must be in 0..1000 m")] = 1.0
    loss_db: Annotated[float, In(0, 200, "must be in 0..200 dB")] = 40.0
    top_m: Annotated[float, In(0, 10_000, "must be in 0..10000 m")] = 1000.0


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class RadioConfig:
    """The radio map (docs/radio.md): path loss from each site, a loss behind the world's obstacles,
    coverage holes, interference that rises with height; link adaptation turns the SINR into a rate."""

    enabled: bool = False
    world_file: str = ""  # the obstacles that shadow the signal ("": the simulator's default arena)
    sites: tuple[RadioSiteConfig, ...] = (RadioSiteConfig(),)
    carrier_ghz: Annotated[float, In(0.4, 100, "must be in 0.4..100 GHz")] = 3.5
    path_loss_exponent: Annotated[float, In(1.5, 6, "must be in 1.5..6")] = 2.0  # line of sight to the air
    obstacle_loss_db: Annotated[float, In(0, 200, "must be in 0..200 dB")] = 15.0
    # noise and the neighbouring cells' interference per resource element, at the ground
    interference_dbm: Annotated[float, In(-174, 0, "must be in -174..0 dBm")] = -95.0
    # a higher drone sees more cells in line of sight, so more interference (3GPP TR 36.777)
    interference_db_per_m: Annotated[float, In(0, 10, "must be in 0..10 dB/m")] = 1.0
    holes: tuple[CoverageHoleConfig, ...] = ()
    # the SINR at which a drone gets the cell's nominal rate (uplink_mbps is the cell's capacity there)
    reference_sinr_db: Annotated[float, In(-10, 40, "must be in -10..40 dB")] = 15.0
    # where the cell hears the vehicles' MAVLink telemetry (their ground-station port; 0: any free port)
    position_port: Annotated[int, In(0, 65535, "must be 0..65535")] = 14550
    position_host: str = "127.0.0.1"
    # whose UE each vehicle is: MAVLink system id -> drone id (empty: the cell's drones in order, 1, 2, ...)
    system_ids: dict[str, int] = field(default_factory=dict)
    update_interval_s: Annotated[float, In(0.01, 10, "must be in 0.01..10 s")] = 0.1
    # a drone not heard for this long has no position: it keeps the nominal rate and reports nothing
    position_timeout_s: Annotated[float, In(0.1, 600, "must be in 0.1..600 s")] = 2.0

    def __post_init__(self) -> None:
        _require(bool(self.sites), "sites", "a radio map needs at least one site")
        names = [s.name for s in self.sites]
        _require(len(set(names)) == len(names), "sites", "site names must be unique")
        for uav, sysid in self.system_ids.items():
            _require(UAV_ID_PATTERN.fullmatch(uav) is not None, f"system_ids.{uav}", "must be a drone id")
            _require(1 <= sysid <= 255, f"system_ids.{uav}", "must be a MAVLink system id in 1..255")
        ids = list(self.system_ids.values())
        _require(len(set(ids)) == len(ids), "system_ids", "each drone needs its own system id")


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class PredictionConfig:
    """The emulated operator's CAMARA Predictive Connectivity Data (0.1.0), predicted from the radio map
    and the cell's scheduled background load with an error (docs/radio.md). Served on the control port
    while [cell.radio] is enabled."""

    # where the world's origin is on the earth: its x axis points north, its y axis east
    origin_lat_deg: Annotated[float, In(-80, 80, "must be in -80..80 degrees")] = 45.0
    origin_lon_deg: Annotated[float, In(-180, 180, "must be in -180..180 degrees")] = 10.0
    slot_s: Annotated[float, In(1, 3600, "must be in 1..3600 s")] = 10.0  # the time slots' length
    layer_thickness_m: Annotated[float, In(0.5, 250, "must be in 0.5..250 m")] = 2.0
    max_height_m: Annotated[float, In(0.5, 250, "must be in 0.5..250 m")] = 8.0  # layers above: ND
    precisions: tuple[int, ...] = (8, 9)  # the geohash levels answered (others: UNSUPPORTED_PRECISION)
    error_db: Annotated[float, In(0, 30, "must be in 0..30 dB")] = 3.0  # the predicted SINR's error (sigma)
    seed: int = 0
    # what each service level needs from the drone's uplink (Mbit/s): good connectivity (GC) is twice it
    c2_mbps: Annotated[float, In(0.01, 1e4, "must be in 0.01..10000")] = 1.0
    stream_4k_mbps: Annotated[float, In(0.01, 1e4, "must be in 0.01..10000")] = 25.0
    good_margin: Annotated[float, In(1, 100, "must be in 1..100")] = 2.0
    horizon_s: Annotated[float, In(1, 86400 * 30, "must be in 1 s..30 days")] = 3600.0  # latest startTime
    max_period_s: Annotated[float, In(1, 86400 * 30, "must be in 1 s..30 days")] = 3600.0
    max_values: Annotated[int, In(1, 10**7, "must be in 1..10000000")] = 200_000  # cells x layers x slots

    def __post_init__(self) -> None:
        _require(
            bool(self.precisions) and all(1 <= p <= 12 for p in self.precisions),
            "precisions",
            "geohash levels are 1..12",
        )
