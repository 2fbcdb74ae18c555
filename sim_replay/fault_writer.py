"""Writing the damaged copy planned by sim_replay.faults: edited lists, damaged
images, attitude faults and shifted clocks; every other file copied as is.
"""

from __future__ import annotations

import math
import os
import shutil
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from sim_replay.fault_plan import (
    CORRUPT_BYTES,
    CORRUPT_OFFSET,
    KINDS,
    SPIKE_DEG,
    Frame,
    Plan,
    Row,
    read_rows,
    write_rows,
)
from sim_replay.outdir import FAULTS_MANIFEST, SIM_MANIFEST


class _Record:
    """What was done, per kind, in the copy's clock (for faults.json)."""

    def __init__(self, jumps: list[tuple[float, float]]) -> None:
        self.jumps = jumps
        self.done: dict[str, dict[str, Any]] = {
            k: {"kind": k, "stamps": [], "files": []} for k in KINDS
        }

    def note(self, kind: str, stamp: float, file: str | None = None, **extra: float) -> None:
        entry = self.done[kind]
        entry["stamps"].append(_shift_stamp(stamp, self.jumps))
        if file:
            entry["files"].append(file)
        for key, value in extra.items():
            entry.setdefault(key, []).append(value)

    def manifest(self, items) -> list[dict[str, Any]]:
        kinds = list(dict.fromkeys(i.kind for i in items))  # in spec order, once each
        return [self.done[k] | {"spec": ",".join(i.text() for i in items if i.kind == k)}
                for k in kinds]


def apply_plan(src: Path, dst: Path, plan: Plan, items, frames: list[Frame], rgb: list[Row],
           depth: list[Row], att: list[Row] | None, camera, rng: np.random.Generator
           ) -> list[dict[str, Any]]:
    record = _Record(plan.jumps)
    new_rgb, new_depth = _apply_lists(dst, plan, frames, rgb, depth, record)
    damaged = _damaged_images(src, plan, frames, rgb, depth, camera, rng, record)
    # Every file still listed is copied; the damaged ones are written afresh
    # (never through a link to the source).
    for f in sorted({r.file for r in (*new_rgb, *new_depth) if r.stamp is not None}):
        _copy_file(src, dst, f, damaged.get(f))
    if att is not None:
        _apply_attitude(dst, plan, att, rng, record)
    for t_j, dt in plan.jumps:
        # The jump point itself, on the source's clock (the first stamp moved is after it).
        record.done["clock-jump"]["stamps"].append(t_j)
        record.done["clock-jump"].setdefault("seconds", []).append(dt)
    _copy_other_files(src, dst, plan.jumps, skip={"attitude.txt"} if att is not None else set())
    if not (src / "camera.toml").is_file():
        _write_camera_toml(dst / "camera.toml", camera)
    return record.manifest(items)


def _apply_lists(dst: Path, plan: Plan, frames: list[Frame], rgb: list[Row],
                 depth: list[Row], record: _Record) -> tuple[list[Row], list[Row]]:
    """rgb.txt and depth.txt with frames dropped, repeated or swapped."""
    for kind, ks in (("drop", plan.drop), ("dup", plan.dup), ("swap", plan.swap)):
        for k in sorted(ks):
            record.note(kind, frames[k].t_s)
    out = []
    for rows, row_of in ((rgb, lambda f: f.rgb_row), (depth, lambda f: f.depth_row)):
        edited = _edit_list(
            rows,
            drop={row_of(frames[k]) for k in plan.drop},
            dup={row_of(frames[k]) for k in plan.dup},
            swap={row_of(frames[k]): row_of(frames[k + 1]) for k in plan.swap},
            jumps=plan.jumps,
        )
        out.append(edited)
    write_rows(dst / "rgb.txt", out[0])
    write_rows(dst / "depth.txt", out[1])
    return out[0], out[1]


def _damaged_images(src: Path, plan: Plan, frames: list[Frame], rgb: list[Row],
                    depth: list[Row], camera, rng: np.random.Generator, record: _Record
                    ) -> dict[str, bytes]:
    """The bytes of every damaged image file, by its listed name."""
    damaged: dict[str, bytes] = {}
    for k in sorted(plan.truncate):
        f = rgb[frames[k].rgb_row].file
        data = (src / f).read_bytes()
        damaged[f] = data[: len(data) // 2]
        record.note("truncate", frames[k].t_s, f)
    for k in sorted(plan.corrupt):
        f = depth[frames[k].depth_row].file
        damaged[f] = _corrupt((src / f).read_bytes(), rng)
        record.note("corrupt", frames[k].t_s, f)
    zeros = cv2.imencode(".png", np.zeros((camera.height, camera.width), np.uint16))[1].tobytes()
    for k in sorted(plan.zero_depth):
        f = depth[frames[k].depth_row].file
        damaged[f] = zeros
        record.note("zero-depth", frames[k].t_s, f)
    return damaged


def _apply_attitude(dst: Path, plan: Plan, att: list[Row], rng: np.random.Generator,
                    record: _Record) -> None:
    """attitude.txt with gaps cut out, NaN and spike samples."""
    out = []
    for k, row in enumerate(att):
        if row.stamp is not None and any(a <= row.stamp < b for a, b in plan.att_gaps):
            continue
        if k in plan.att_nan:
            row = Row(f"{row.stamp_text} nan nan nan nan", row.stamp, row.stamp_text)
            record.note("att-nan", row.stamp)
        elif k in plan.att_spike:
            row = _spike(row, rng)
            record.note("att-spike", row.stamp)
        out.append(_shift_row(row, plan.jumps))
    write_rows(dst / "attitude.txt", out)
    for a, b in plan.att_gaps:
        record.note("att-gap", a, until=_shift_stamp(b, plan.jumps))


def _corrupt(data: bytes, rng: np.random.Generator) -> bytes:
    """Garbage in the middle of the first PNG IDAT payload, chunk lengths and
    CRC fields untouched: the file looks whole, its checksum fails, libpng
    refuses it. Other formats get garbage right after the first 16 bytes."""
    out = bytearray(data)
    start = CORRUPT_OFFSET
    if data.startswith(b"\x89PNG\r\n\x1a\n"):
        pos = 8
        while pos + 12 <= len(data):
            length = int.from_bytes(data[pos:pos + 4], "big")
            if data[pos + 4:pos + 8] == b"IDAT" and length > CORRUPT_BYTES:
                start = pos + 8 + (length - CORRUPT_BYTES) // 2
                break
            pos += 12 + length
    end = min(start + CORRUPT_BYTES, len(out))
    out[start:end] = rng.integers(0, 256, end - start, dtype=np.uint8).tobytes()
    return bytes(out)


def _edit_list(rows: list[Row], drop: set[int], dup: set[int], swap: dict[int, int],
               jumps: list[tuple[float, float]]) -> list[Row]:
    order = list(range(len(rows)))
    for a, b in swap.items():
        ia, ib = order.index(a), order.index(b)
        order[ia], order[ib] = order[ib], order[ia]
    out = []
    for k in order:
        if k in drop:
            continue
        row = _shift_row(rows[k], jumps)
        out.append(row)
        if k in dup:
            out.append(row)
    return out


def _shift_stamp(t: float, jumps: list[tuple[float, float]]) -> float:
    return t + sum(dt for t_j, dt in jumps if t >= t_j)


def _shift_row(row: Row, jumps: list[tuple[float, float]]) -> Row:
    if row.stamp is None:
        return row
    dt = sum(d for t_j, d in jumps if row.stamp >= t_j)
    return row.shifted(dt) if dt else row


def _spike(row: Row, rng: np.random.Generator) -> Row:
    parts = row.text.split()
    try:
        q = Rotation.from_quat([float(v) for v in parts[1:5]])
    except (ValueError, IndexError):
        return row
    axis = rng.standard_normal(3)
    angle = math.radians(rng.uniform(*SPIKE_DEG))
    qs = (q * Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle)).as_quat()
    return Row(f"{row.stamp_text} {qs[0]:.9f} {qs[1]:.9f} {qs[2]:.9f} {qs[3]:.9f}",
                row.stamp, row.stamp_text)


def _copy_file(src: Path, dst: Path, rel: str, data: bytes | None) -> None:
    """Copy one listed file; paths leaving the folder are left alone (they
    would read the source itself, which stays untouched)."""
    rel_path = Path(rel)
    if rel_path.is_absolute() or ".." in rel_path.parts:
        return
    source = src / rel_path
    target = dst / rel_path
    if data is None and not source.is_file():
        return  # missing in the source: stays missing
    target.parent.mkdir(parents=True, exist_ok=True)
    if data is not None:
        target.write_bytes(data)
    else:
        shutil.copyfile(source, target)


def _copy_other_files(src: Path, dst: Path, jumps, skip: set[str]) -> None:
    """Top-level files besides the lists: text files with leading stamps get
    the clock jump too (ground truth, accelerometer...); manifests of the
    source are not copied (the copy is not the source's flight any more)."""
    for p in sorted(src.iterdir()):
        if not p.is_file() or p.name in skip | {"rgb.txt", "depth.txt", SIM_MANIFEST,
                                                 FAULTS_MANIFEST}:
            continue
        if p.suffix == ".txt" and jumps:
            write_rows(dst / p.name, [_shift_row(r, jumps)
                                       for r in read_rows(p, with_file=False)])
        else:
            shutil.copyfile(p, dst / p.name)


def _write_camera_toml(path: Path, camera) -> None:
    lines = [
        "# written by nislam fault injection: the source's camera (from its folder name)",
        f"fx = {camera.fx!r}", f"fy = {camera.fy!r}", f"cx = {camera.cx!r}",
        f"cy = {camera.cy!r}", f"width = {camera.width}", f"height = {camera.height}",
        f"depth_scale = {camera.depth_scale!r}",
    ]
    if camera.distortion:
        lines.append(f"distortion = [{', '.join(repr(c) for c in camera.distortion)}]")
    q = camera.q_B_C_xyzw
    lines.append(f"q_B_C_xyzw = [{', '.join(repr(float(c)) for c in q)}]")
    path.write_text("\n".join(lines) + "\n")
    os.chmod(path, 0o644)
