"""`dynqos store`: a run folder thinned for committing loses its repeats, never a figure, and says where
each left-out summary still is."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest

from dynqos.cli.main import main
from dynqos.reports.store import canonical, store


def entry(value: Any, path: str) -> Any:
    """The entry of a JSON value at a STORED.md path such as `scenarios[0].runs[1]`."""
    for key, index in re.findall(r"\.?([A-Za-z_][\w-]*)|\[(\d+)\]", path):
        value = value[key] if key else value[int(index)]
    return value


def seed(n: int, rtt: float) -> dict[str, Any]:
    return {"seed": n, "rtt_ms": {"loaded": {"mean": rtt, "p95": rtt * 1.5}}, "ok": True}


def plot(path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot([0, 1, 2, 3], [1.0, 3.0, 2.0, 4.0], label="C&C RTT")
    ax.plot([0, 1, 2, 3], [2.0, 1.0, 3.0, 2.5], label="camera")
    ax.legend()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


@pytest.fixture
def run(tmp_path: Path) -> Path:
    """A demo's folder: the run's summary holds each scenario's, which holds each seed's; one seed's
    file differs from its entry (it must stay), one scenario has a config and series."""
    root = tmp_path / "run"
    scenario = {"scenario": "bg-dynqos", "runs": [seed(0, 15.2), seed(1, 16.8)], "ok": True}
    top = {"scenarios": [scenario], "ok": True, "wall_time_s": 61.0}
    files = {
        "summary.json": top,
        "bg-dynqos/summary.json": scenario,
        "bg-dynqos/seed0/summary.json": seed(0, 15.2),
        "bg-dynqos/seed1/summary.json": seed(1, 16.9),  # not the entry: kept
        "bg-dynqos/seed0/qod.json": {"session": "abc"},
    }
    for name, value in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(json.dumps(value, indent=2) + "\n")
    (root / "bg-dynqos" / "seed0" / "states.csv").write_text("t,x\n0,1\n")
    (root / "bg-dynqos" / "seed0" / "dynqos.toml").write_text("[control]\nt_mpc_s = 0.05\n")
    (root / "bg-dynqos" / "seed1" / "dynqos.toml").write_text("[control]\nt_mpc_s = 0.05\n")
    (root / "report.md").write_text("# report\n")
    plot(root / "bg-dynqos" / "seed0" / "overview.png")
    plot(root / "bg-dynqos" / "seed1" / "overview.png")
    return root


def test_repeats_go_and_every_figure_stays_where_stored_md_says(run: Path, tmp_path: Path) -> None:
    dest = tmp_path / "stored"
    result = store(run, dest, today="2026-12-08")
    kept = {str(p) for p in result.kept}
    assert "summary.json" in kept
    assert "bg-dynqos/seed1/summary.json" in kept
    assert "bg-dynqos/seed0/qod.json" in kept
    assert "bg-dynqos/seed0/dynqos.toml" in kept
    assert not (dest / "bg-dynqos" / "summary.json").exists()
    assert not (dest / "bg-dynqos" / "seed0" / "summary.json").exists()
    note = (dest / "STORED.md").read_text()
    top = json.loads((dest / "summary.json").read_text())
    located = re.findall(r"^- `([^`]+)`: `([^`]+)`, at `([^`]+)`", note, flags=re.M)
    assert {name for name, _, _ in located} == {"bg-dynqos/summary.json", "bg-dynqos/seed0/summary.json"}
    for name, holder, path in located:
        held = json.loads((dest / holder).read_text())
        assert entry(held, path) == json.loads((run / name).read_text()), name
    assert top == json.loads((run / "summary.json").read_text())
    assert "\n" not in (dest / "summary.json").read_text().rstrip("\n")  # compact


def test_series_and_later_seeds_plots_and_configs_go_and_the_plot_stays_a_plot(
    run: Path, tmp_path: Path
) -> None:
    from PIL import Image

    thin = store(run, tmp_path / "thin")
    assert [str(p) for p in thin.series] == ["bg-dynqos/seed0/states.csv"]
    assert [str(p) for p in thin.later_seeds] == [
        "bg-dynqos/seed1/dynqos.toml",
        "bg-dynqos/seed1/overview.png",
    ]
    assert "states.csv" in (tmp_path / "thin" / "STORED.md").read_text()
    before, after = run / "bg-dynqos/seed0/overview.png", tmp_path / "thin/bg-dynqos/seed0/overview.png"
    assert after.stat().st_size < before.stat().st_size
    with Image.open(before) as a, Image.open(after) as b:
        assert a.size == b.size
        assert b.mode == "P"
        # the same picture: no pixel far from the original
        original, stored = a.convert("RGB"), b.convert("RGB")
        worst = max(
            max(abs(x - y) for x, y in zip(original.getpixel((i, j)), stored.getpixel((i, j)), strict=True))
            for i in range(0, a.size[0], 7)
            for j in range(0, a.size[1], 7)
        )
        assert worst < 64
    kept = store(run, tmp_path / "kept", keep_series=True)
    assert not kept.series
    assert (tmp_path / "kept" / "bg-dynqos/seed0/states.csv").exists()


def test_a_summary_is_dropped_only_below_the_file_that_holds_it(tmp_path: Path) -> None:
    """A sibling folder's file with the same value is not a repeat: nothing above it holds it."""
    root = tmp_path / "run"
    for folder in ("a", "b"):
        (root / folder).mkdir(parents=True)
        (root / folder / "summary.json").write_text(json.dumps({"x": [1, 2]}))
    result = store(root, tmp_path / "out")
    assert not result.repeats
    assert len(result.kept) == 2


def test_canonical_ignores_key_order_but_not_values() -> None:
    where: dict[bytes, str] = {}
    assert canonical({"b": 1, "a": [1.5]}, where) == canonical({"a": [1.5], "b": 1}, {})
    assert canonical({"a": 1.0}, {}) != canonical({"a": 1}, {})
    assert sorted(where.values()) == ["", "a"]


def test_the_command_says_what_it_did_and_refuses_bad_folders(
    run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    dest = tmp_path / "stored"
    assert main(["store", str(run), str(dest)]) == 0
    assert "left out 2 repeated JSON files" in capsys.readouterr().out
    assert main(["store", str(run), str(dest)]) == 2
    assert "already exists" in capsys.readouterr().err
    assert main(["store", str(tmp_path / "nowhere"), str(tmp_path / "x")]) == 2
    assert "not a folder" in capsys.readouterr().err
