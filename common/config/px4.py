"""`[px4]`: a real PX4 SITL in place of dynqos's simulated vehicle (docs/px4.md).

The folder is one with `bin/px4` and `etc/`: a `make px4_sitl` build (PX4's `build/px4_sitl_default`)
or a packaged SITL. What PX4 itself is set to at boot are its own parameters (`params`), over the ones
dynqos flies with (sim/vehicle/px4_sitl.py, `DYNQOS_PARAMETERS`)."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Annotated

from dynqos.common.config.validate import In, _require, checked

PARAM_NAME = re.compile(r"[A-Z][A-Z0-9_]{0,15}")  # PX4's names: 16 characters at most


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class Px4Config:
    """Where PX4 is and how each instance boots."""

    dir: str = ""  # PX4's folder ("" = none: --vehicle px4 says how to set it)
    # Parameters at boot (PX4_PARAM_<NAME>), over dynqos's; e.g. {COM_OBL_RC_ACT = 5}
    params: dict[str, float] = field(default_factory=dict)
    # Seconds from start to PX4's "Startup script returned successfully"
    boot_timeout_s: Annotated[float, In(1, 300, "must be in 1..300 s")] = 30.0
    ulog: bool = True  # PX4's logger writes a ULog into the instance's working directory
    # A MAVLink signing key (`dynqos signing-key`) PX4 boots with, as it would keep one provisioned on its
    # SD card: then PX4 signs what it sends and drops unsigned commands ("" = off; docs/px4.md)
    signing_key: str = ""

    def __post_init__(self) -> None:
        for name in self.params:
            _require(
                PARAM_NAME.fullmatch(name) is not None,
                "params",
                f"{name!r} is not a PX4 parameter name (A-Z, 0-9 and _, at most 16)",
            )
