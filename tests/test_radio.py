"""The radio map and link adaptation (sim/network/radio.py) and what they do to the scheduler
(sim/network/cell_core.py): pure, on made-up positions and a made-up clock."""

from __future__ import annotations

import math

import pytest

from dynqos.common.config import (
    BackgroundConfig,
    CellConfig,
    CoverageHoleConfig,
    RadioConfig,
    RadioSiteConfig,
    build,
)
from dynqos.common.errors import ConfigError
from dynqos.sim.network.cell_core import CellCore
from dynqos.sim.network.radio import CQI_EFFICIENCY, CQI_THRESHOLDS_DB, RadioMap, cqi, efficiency
from dynqos.sim.vehicle.world import Cylinder, World

MS = 1_000_000
PILLAR = Cylinder(center_m=(0.0, 0.0), radius_m=1.0, z_top_m=-4.0)
SITE = RadioSiteConfig(position_m=(-300.0, 0.0, -25.0))


def radio_map(**config: object) -> RadioMap:
    return RadioMap(RadioConfig(enabled=True, sites=(SITE,), **config), World(cylinders=(PILLAR,)))  # type: ignore[arg-type]


def test_link_adaptation_follows_the_cqi_table_and_its_thresholds_rise() -> None:
    assert list(CQI_THRESHOLDS_DB) == sorted(CQI_THRESHOLDS_DB)
    assert CQI_THRESHOLDS_DB[0] == pytest.approx(-7.2, abs=0.1)
    assert CQI_THRESHOLDS_DB[-1] == pytest.approx(27.9, abs=0.1)
    assert cqi(-20.0) == 0
    assert efficiency(-20.0) == 0.0
    assert cqi(CQI_THRESHOLDS_DB[6]) == 7
    assert efficiency(CQI_THRESHOLDS_DB[6]) == CQI_EFFICIENCY[6]
    assert cqi(CQI_THRESHOLDS_DB[6] - 0.01) == 6
    assert cqi(60.0) == 15


def test_the_signal_falls_with_distance_behind_an_obstacle_and_in_a_hole() -> None:
    m = radio_map(holes=(CoverageHoleConfig(center_m=(0.0, -20.0), radius_m=3.0, edge_m=2.0, loss_db=40.0),))
    open_air = m.at((0.0, 8.0, -1.5))
    farther = m.at((300.0, 8.0, -1.5))
    assert farther.rsrp_dbm == pytest.approx(open_air.rsrp_dbm - 20 * math.log10(600 / 300), abs=0.2)
    shadowed = m.at((3.0, 0.0, -1.5))  # the pillar between the drone and the site, west of it
    lit = m.at((-3.0, 0.0, -1.5))  # the same distance from the pillar, on the site's side
    assert lit.rsrp_dbm - shadowed.rsrp_dbm == pytest.approx(15.0, abs=0.2)
    assert m.at((3.0, 0.0, -5.0)).rsrp_dbm > shadowed.rsrp_dbm + 14  # above the pillar's top: seen again
    hole, edge = m.at((0.0, -20.0, -1.5)), m.at((0.0, -24.0, -1.5))  # the centre, half-way through the edge
    assert hole.cqi == 0
    assert hole.rate_factor == 0.0
    assert open_air.rsrp_dbm - edge.rsrp_dbm == pytest.approx(20.0, abs=0.5)
    assert m.at((0.0, -26.0, -1.5)).rsrp_dbm == pytest.approx(open_air.rsrp_dbm, abs=0.5)


def test_interference_rises_with_height_and_the_rate_factor_is_one_at_the_reference() -> None:
    m = radio_map()
    low, high = m.at((0.0, 8.0, -1.0)), m.at((0.0, 8.0, -11.0))
    assert low.rsrp_dbm == pytest.approx(high.rsrp_dbm, abs=0.1)
    assert low.sinr_db - high.sinr_db == pytest.approx(10.0, abs=0.1)  # 1 dB per metre by default
    assert high.rate_factor < low.rate_factor
    at_reference = radio_map(reference_sinr_db=low.sinr_db).at((0.0, 8.0, -1.0))
    assert at_reference.rate_factor == 1.0


def test_the_strongest_site_serves() -> None:
    near = RadioSiteConfig(name="near", position_m=(50.0, 0.0, -25.0))
    m = RadioMap(RadioConfig(enabled=True, sites=(SITE, near)))
    assert m.at((40.0, 0.0, -2.0)).site == "near"
    assert m.at((-250.0, 0.0, -2.0)).site == "site1"


def test_the_scheduler_shares_resources_so_a_poor_radio_gets_fewer_bits() -> None:
    config = CellConfig(uplink_mbps=10.0, background=(BackgroundConfig(name="bg", offered_mbps=100.0),))
    c = CellCore(config, {"uav1-default": 1.0, "uav2-default": 1.0}, 0)
    c.rate_factors = {"uav1-default": 1.0, "uav2-default": 0.25}
    total = dict.fromkeys(("uav1-default", "uav2-default", "bg:bg"), 0.0)
    for t in range(1, 1001):
        for name, bits in c.step(t * MS, {"uav1-default": 1e6, "uav2-default": 1e6}).items():
            total[name] += bits
    # a third of the resources each; uav2's third carries a quarter of the bits
    assert total["uav1-default"] == pytest.approx(10e6 / 3, rel=0.02)
    assert total["uav2-default"] == pytest.approx(10e6 / 3 / 4, rel=0.02)
    assert total["bg:bg"] == pytest.approx(10e6 / 3, rel=0.02)
    c.rate_factors = {"uav1-default": 1.0, "uav2-default": 0.0}  # out of coverage: none, the rest shared
    grants = c.step(1001 * MS, {"uav1-default": 1e6, "uav2-default": 1e6})
    assert grants["uav2-default"] == 0.0
    assert grants["uav1-default"] == pytest.approx(10e3 / 2, rel=0.02)


@pytest.mark.parametrize(
    ("table", "message"),
    [
        ({"sites": []}, "radio.sites: a radio map needs at least one site"),
        ({"system_ids": {"uav1": 300}}, "radio.system_ids.uav1: must be a MAVLink system id in 1..255"),
        ({"system_ids": {"uav1": 1, "uav2": 1}}, "radio.system_ids: each drone needs its own system id"),
        ({"holes": [{"center_m": [0, 0], "loss_db": -1}]}, "radio.holes[0].loss_db: must be in 0..200 dB"),
    ],
)
def test_a_bad_radio_config_names_its_key(table: dict[str, object], message: str) -> None:
    with pytest.raises(
        ConfigError, match=message.replace("[", r"\[").replace("]", r"\]").replace(".", r"\.")
    ):
        build(CellConfig, {"radio": table})
