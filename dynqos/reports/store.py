"""A run folder, thinned to what is worth committing (`dynqos store`, docs/development.md).

A flight's folder repeats itself: each seed's summary.json is one entry of its scenario's summary, which
is one entry of the run's. Committed as written, the stored runs under docs/ reached 39 MB. Thinning
keeps every figure: a JSON file is left out only where a kept JSON file in the same folder or above it
holds the very same value, so each figure stays traceable to a summary that is still there. JSON is
written compact, and a plot is re-encoded with a small palette (matplotlib's flat lines need few
colours). The raw series (CSV files and logs) stay only when asked for: the summaries hold the figures,
and the same command at the same commit flies them again.
"""

from __future__ import annotations

import hashlib
import io
import json
import re
import shutil
from dataclasses import dataclass, field
from datetime import date
from pathlib import Path
from typing import Any

from dynqos.common.errors import DynqosError

PALETTE_COLOURS = 16  # a plot's series and its anti-aliased edges
SERIES_SUFFIXES = frozenset({".csv", ".log", ".jsonl", ".ulg", ".bin", ".mcap"})
SEED_FOLDER = re.compile(r"seed(\d+)")
NOTE = "STORED.md"
# a later seed's plots, and its config, which differs from the first seed's in its seed and ports
LATER_SEEDS_LEFT_OUT = frozenset({".png", ".toml"})


@dataclass(frozen=True)
class Repeat:
    """A JSON file left out, and where its value still is: `holder`'s entry at `path`."""

    holder: Path
    path: str

    def describe(self) -> str:
        return f"`{self.holder}`" + (f", at `{self.path}`" if self.path else " (the same value)")


@dataclass
class StoreResult:
    """What a thinning did, for the one line `dynqos store` prints and for tests."""

    kept: list[Path] = field(default_factory=list)
    repeats: dict[Path, Repeat] = field(default_factory=dict)  # a JSON file left out -> where it is
    series: list[Path] = field(default_factory=list)  # CSV files and logs left out
    later_seeds: list[Path] = field(default_factory=list)  # plots and configs of seeds past the first
    bytes_before: int = 0
    bytes_after: int = 0

    def describe(self) -> str:
        return (
            f"kept {len(self.kept)} files, {self.bytes_before / 1e6:.2f} -> {self.bytes_after / 1e6:.2f} MB; "
            f"left out {len(self.repeats)} repeated JSON files, {len(self.series)} raw series or logs "
            f"and {len(self.later_seeds)} plots or configs of later seeds"
        )


def canonical(value: Any, where: dict[bytes, str], path: str = "") -> str:
    """`value` as canonical JSON; `where` gets the digest of every object and array inside it, with its
    path (`scenarios[2].runs[0]`; "" for the whole).

    Built bottom-up, so a large summary is walked once rather than once per level."""
    if isinstance(value, dict):
        inner = (f"{json.dumps(k)}:{canonical(value[k], where, _join(path, k))}" for k in sorted(value))
        text = "{" + ",".join(inner) + "}"
    elif isinstance(value, list):
        text = "[" + ",".join(canonical(item, where, f"{path}[{i}]") for i, item in enumerate(value)) + "]"
    else:
        return json.dumps(value)
    where.setdefault(_digest(text), path)
    return text


def _join(path: str, key: str) -> str:
    step = key if re.fullmatch(r"[A-Za-z_][\w-]*", key) else json.dumps(key)
    return f"{path}.{step}" if path else step


def _digest(text: str) -> bytes:
    return hashlib.sha256(text.encode()).digest()


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError):
        return None  # not JSON after all: copied as it is


def _json_order(path: Path, root: Path) -> tuple[int, str, int, str]:
    """Shallow folders first (a run's summary before its scenarios'), and in one folder the larger
    file first, so that the file holding another is the one kept."""
    rel = path.relative_to(root)
    return (len(rel.parts), str(rel.parent), -path.stat().st_size, path.name)


def _first_seeds(files: list[Path]) -> set[Path]:
    """Each scenario's first seed folder: the one whose plots and config are kept."""
    lowest: dict[Path, tuple[int, Path]] = {}
    for path in files:
        match = SEED_FOLDER.fullmatch(path.parent.name)
        if match:
            seed = int(match.group(1))
            here = lowest.get(path.parent.parent)
            if here is None or seed < here[0]:
                lowest[path.parent.parent] = (seed, path.parent)
    return {folder for _, folder in lowest.values()}


def _is_later_seeds(path: Path, first_seeds: set[Path]) -> bool:
    return (
        path.suffix in LATER_SEEDS_LEFT_OUT
        and bool(SEED_FOLDER.fullmatch(path.parent.name))
        and (path.parent not in first_seeds)
    )


def plan_json(root: Path, files: list[Path]) -> tuple[dict[Path, Any], dict[Path, Repeat]]:
    """The JSON files to keep (with their values) and, for each one left out, where its value is kept."""
    kept: dict[Path, Any] = {}
    holders: list[tuple[Path, dict[bytes, str]]] = []
    repeats: dict[Path, Repeat] = {}
    for path in sorted((p for p in files if p.suffix == ".json"), key=lambda p: _json_order(p, root)):
        value = _read_json(path)
        if value is None or not isinstance(value, (dict, list)):
            continue
        where: dict[bytes, str] = {}
        whole = _digest(canonical(value, where))
        for holder, held in holders:
            if path.parent.is_relative_to(holder.parent) and whole in held:
                repeats[path] = Repeat(holder.relative_to(root), held[whole])
                break
        else:
            kept[path] = value
            holders.append((path, where))
    return kept, repeats


def _write_plot(src: Path, dest: Path) -> None:
    """The plot with a palette where that is smaller; the file as it is without Pillow or where not."""
    try:
        from PIL import Image
    except ImportError:
        shutil.copyfile(src, dest)
        return
    with Image.open(src) as image:
        rgba = image.convert("RGBA")
    flat = Image.new("RGBA", rgba.size, (255, 255, 255, 255))
    flat.alpha_composite(rgba)
    buffer = io.BytesIO()
    flat.convert("RGB").quantize(PALETTE_COLOURS, dither=Image.Dither.NONE).save(
        buffer, format="PNG", optimize=True
    )
    if buffer.tell() < src.stat().st_size:
        dest.write_bytes(buffer.getvalue())
    else:
        shutil.copyfile(src, dest)


def store(src: Path, dest: Path, keep_series: bool = False, today: str | None = None) -> StoreResult:
    """Copy the run folder `src` into `dest` (which must not exist yet), thinned, with STORED.md saying
    what was left out and where each left-out summary's value is kept."""
    if not src.is_dir():
        raise DynqosError(f"{src}: not a folder (give the run's folder, e.g. runs/<date-time>)")
    if dest.exists():
        raise DynqosError(f"{dest}: already exists; give a new folder (nothing was written)")
    files = sorted(p for p in src.rglob("*") if p.is_file() and not p.is_symlink())
    kept_json, repeats = plan_json(src, files)
    first_seeds = _first_seeds(files)
    result = StoreResult(repeats={p.relative_to(src): r for p, r in repeats.items()})
    for path in files:
        rel = path.relative_to(src)
        result.bytes_before += path.stat().st_size
        if path in repeats or rel == Path(NOTE):
            continue
        if path.suffix in SERIES_SUFFIXES and not keep_series:
            result.series.append(rel)
            continue
        if _is_later_seeds(path, first_seeds):
            result.later_seeds.append(rel)
            continue
        target = dest / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        if path in kept_json:
            target.write_text(json.dumps(kept_json[path], separators=(",", ":")) + "\n")
        elif path.suffix == ".png":
            _write_plot(path, target)
        else:
            shutil.copyfile(path, target)
        result.kept.append(rel)
        result.bytes_after += target.stat().st_size
    earlier = (src / NOTE).read_text() + "\n" if (src / NOTE).is_file() else ""
    dest.mkdir(parents=True, exist_ok=True)
    (dest / NOTE).write_text(earlier + stored_note(result, today or date.today().isoformat()))
    return result


def stored_note(result: StoreResult, today: str) -> str:
    """STORED.md: how the folder was thinned, and where each summary left out still is."""
    lines = [
        f"# Stored with `dynqos store` ({today})",
        "",
        f"{result.describe()}. JSON is written compact and each plot with a {PALETTE_COLOURS}-colour "
        "palette; no figure was changed.",
    ]
    if result.repeats:
        lines += ["", "Each of these JSON files held exactly the value of a kept file's entry:", ""]
        lines += [f"- `{path}`: {repeat.describe()}" for path, repeat in sorted(result.repeats.items())]
    for title, paths in (
        (
            "Raw series and logs left out (the same command at the same commit writes them):",
            result.series,
        ),
        (
            "Plots and configs of later seeds left out (each scenario keeps its first seed's; a later "
            "seed's config differs in its seed and ports):",
            result.later_seeds,
        ),
    ):
        if paths:
            lines += ["", title, ""] + [f"- `{path}`" for path in sorted(paths)]
    return "\n".join(lines) + "\n"
