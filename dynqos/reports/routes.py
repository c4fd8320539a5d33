"""routes.png of a planned mission (docs/planning.md): each drone's planned legs and the track it flew,
over the SINR the radio map gives at the default height, with the task sites. The map is the cell's
own (the run's [cell.radio] and world), not what the operator predicted."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from dynqos.common.config import Config
from dynqos.sim.network.radio import RadioMap
from dynqos.sim.vehicle.world import load_world

COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:pink")


def plot_routes(folder: Path, plan: dict[str, Any], config: Config, tracks: dict[str, list[Any]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    radio = config.cell.radio
    world = load_world(radio.world_file) if radio.world_file else None
    hx, hy = config.fleet_plan.half_m
    height = config.fleet_plan.heights_m[0]
    xs, ys = np.linspace(-hx, hx, 161), np.linspace(-hy, hy, 161)
    radio_map = RadioMap(radio, world)
    sinr = np.array([[radio_map.at((x, y, -height)).sinr_db for y in ys] for x in xs])
    fig, ax = plt.subplots(figsize=(8, 7))
    mesh = ax.pcolormesh(ys, xs, sinr, cmap="viridis", vmin=-10, vmax=20, shading="auto")
    fig.colorbar(mesh, ax=ax, label=f"SINR at {height:g} m (dB)")
    for i, (uav, legs) in enumerate(sorted(plan["legs"].items())):
        colour = COLOURS[i % len(COLOURS)]
        for leg in legs:
            path = np.array(leg["path_m"])
            high = path[:, 2].max() > height + 0.5
            ax.plot(path[:, 1], path[:, 0], color=colour, lw=2, ls=":" if high else "-")
        track = np.array([(x, y) for _, x, y, _ in tracks.get(uav, [])])
        if len(track):
            ax.plot(track[:, 1], track[:, 0], color=colour, lw=0.8, alpha=0.7)
        start = plan["start_m"].get(uav)
        if start:
            ax.plot(start[1], start[0], "o", color=colour, label=uav)
    for task in plan["tasks"]:
        x, y = task["points_m"][0]
        ax.plot(y, x, "k^" if task["risk"] == "high" else "kx", ms=8)
        ax.annotate(task["id"], (y, x), textcoords="offset points", xytext=(4, 4), fontsize=7, color="white")
    ax.set_xlabel("y east (m)")
    ax.set_ylabel("x north (m)")
    ax.set_aspect("equal")
    ax.set_title(f"{plan['mode']}: planned legs (thick; dotted above {height:g} m) and tracks flown (thin)")
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(folder / "routes.png", dpi=110)
    plt.close(fig)
