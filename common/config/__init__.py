"""Configuration: TOML files loaded into frozen, typed dataclasses, one section per table.

The sections live by concern (`network.py`: drone, zenoh, cell, vehicle, metrics; `control.py`:
supervisor, control, MPC, planner, detector, onboard; `qos.py`: the QoS agent, its operator and its
arbiter; `nef.py`: a 5G core's NEF for the agent); `loader.py` holds the whole `Config`, the TOML
loader with its overrides and the writer.
Everything is imported from here: `from dynqos.common.config import Config, load_config`.
"""

from dynqos.common.config.control import (
    ControlConfig,
    DetectorConfig,
    DroneMissionConfig,
    MpcConfig,
    OnboardConfig,
    OnboardPathConfig,
    PlannerConfig,
    Ros2Config,
    SupervisorConfig,
)
from dynqos.common.config.loader import (
    Config,
    build,
    environment_overrides,
    load_config,
    overlaid,
    to_dict,
    to_toml,
)
from dynqos.common.config.nef import NefConfig, NefUeConfig
from dynqos.common.config.network import (
    BackgroundConfig,
    BearerConfig,
    CellConfig,
    CellEventConfig,
    DroneConfig,
    MetricsConfig,
    VehicleSimConfig,
    ZenohConfig,
)
from dynqos.common.config.planning import FleetPlanConfig, FleetTaskConfig
from dynqos.common.config.px4 import Px4Config
from dynqos.common.config.qos import ArbiterConfig, CamaraConfig, DeviceConfig, DeviceIpv4Config, QosConfig
from dynqos.common.config.radio import CoverageHoleConfig, PredictionConfig, RadioConfig, RadioSiteConfig

__all__ = [
    "ArbiterConfig",
    "BackgroundConfig",
    "BearerConfig",
    "CamaraConfig",
    "CellConfig",
    "CellEventConfig",
    "Config",
    "ControlConfig",
    "CoverageHoleConfig",
    "DetectorConfig",
    "DeviceConfig",
    "DeviceIpv4Config",
    "DroneConfig",
    "DroneMissionConfig",
    "FleetPlanConfig",
    "FleetTaskConfig",
    "MetricsConfig",
    "MpcConfig",
    "NefConfig",
    "NefUeConfig",
    "OnboardConfig",
    "OnboardPathConfig",
    "PlannerConfig",
    "PredictionConfig",
    "Px4Config",
    "QosConfig",
    "RadioConfig",
    "RadioSiteConfig",
    "Ros2Config",
    "SupervisorConfig",
    "VehicleSimConfig",
    "ZenohConfig",
    "build",
    "environment_overrides",
    "load_config",
    "overlaid",
    "to_dict",
    "to_toml",
]
