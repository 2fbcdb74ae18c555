"""What `nislam ground` shows and writes: the one-line-per-vehicle table,
`fleet.json`, each vehicle's map as `<id>.ply` (earlier boots as
`<id>.boot<N>.ply`) and `fleet.png`, every trajectory from above.

Each vehicle's positions are in its own tracker world W (gravity-aligned,
origin where its tracker started): the plot shows them side by side on
shared axes, not registered to each other.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from onboard.outputs.mapcodec import MapKeyframe
from onboard.outputs.ply import write_ply

log = logging.getLogger(__name__)

FLEET_JSON = "fleet.json"
FLEET_PNG = "fleet.png"


@dataclass
class Earlier:
    """A vehicle's map and trajectory from a boot before its restart."""

    boot: str
    keyframes: dict[int, MapKeyframe]
    trajectory: list[tuple[float, float, float, float]]


def map_points(keyframes: Mapping[int, MapKeyframe]) -> tuple[np.ndarray, np.ndarray]:
    """All points of a map, key frames in id order."""
    parts = [keyframes[k].points() for k in sorted(keyframes)]
    if not parts:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def _num(v: float | None, fmt: str) -> str:
    return "-" if v is None else format(v, fmt)


def table_lines(vehicles: Mapping[str, Any], period_s: float) -> list[str]:
    """The live table: one line per vehicle (ground.Vehicle) and a header."""
    head = (f"{'vehicle':<12} {'state':<10} {'Hz':>5} {'lat ms':>7} {'keys':>5} "
            f"{'points':>9} {'pose B/s':>9} {'map kB/s':>9} {'boots':>5} link")
    lines = [head]
    for vid in sorted(vehicles):
        v = vehicles[vid]
        s = v.summary()
        bps = s["bytes_per_s"]
        lines.append(
            f"{vid:<12.12} {v.last_state:<10.10} {v.period_poses / max(period_s, 1e-9):5.1f} "
            f"{_num(s['latency_ms_median'], '7.1f'):>7} {s['keyframes']:5d} "
            f"{s['map_points']:9d} {bps['pose']:9.0f} {bps['map'] / 1e3:9.1f} "
            f"{v.restarts + 1:5d} {'up' if v.alive else 'down'}")
    return lines


def _atomic_text(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")  # then rename: a reader never sees half a file
    tmp.write_text(text)
    os.replace(tmp, path)


def plot_fleet(path: Path, tracks: Iterable[tuple[str, np.ndarray]]) -> bool:
    """Top view (x, y of W) of every trajectory; False without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        from matplotlib.figure import Figure
    except ImportError:
        log.info("matplotlib not importable; no %s", path)
        return False
    fig = Figure(figsize=(8, 8), layout="constrained")
    ax = fig.subplots()
    n = 0
    for label, xyz in tracks:
        if len(xyz):
            line = ax.plot(xyz[:, 0], xyz[:, 1], lw=1.2, label=label)[0]
            ax.plot(xyz[-1, 0], xyz[-1, 1], "o", color=line.get_color())
            n += 1
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.set_title(f"fleet: {n} trajectories, top view (each in its own world)")
    if n:
        ax.legend(loc="best", fontsize="small")
    fig.savefig(path, dpi=100)
    return True


def write_fleet(out_dir: Path, summary: dict[str, Any],
                vehicles: Mapping[str, Any]) -> list[Path]:
    """fleet.json, <id>.ply (+ <id>.boot<N>.ply) and fleet.png in out_dir."""
    out_dir.mkdir(parents=True, exist_ok=True)
    files = [out_dir / FLEET_JSON]
    _atomic_text(files[0], json.dumps(summary, indent=2, allow_nan=False) + "\n")
    tracks: list[tuple[str, np.ndarray]] = []
    for vid in sorted(vehicles):
        v = vehicles[vid]
        path = out_dir / f"{vid}.ply"
        write_ply(path, *map_points(v.keyframes))
        files.append(path)
        for i, e in enumerate(v.earlier):
            path = out_dir / f"{vid}.boot{i + 1}.ply"
            write_ply(path, *map_points(e.keyframes))
            files.append(path)
            tracks.append((f"{vid} (boot {i + 1})", _xyz(e.trajectory)))
        tracks.append((vid if not v.earlier else f"{vid} (boot {len(v.earlier) + 1})",
                       _xyz(v.trajectory)))
    if plot_fleet(out_dir / FLEET_PNG, tracks):
        files.append(out_dir / FLEET_PNG)
    return files


def _xyz(trajectory: list[tuple[float, float, float, float]]) -> np.ndarray:
    return np.asarray(trajectory, dtype=np.float64).reshape(-1, 4)[:, 1:]
