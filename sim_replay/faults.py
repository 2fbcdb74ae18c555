"""Fault injection: write a damaged copy of a TUM-layout recording (synthetic
or recorded). The source is only read, never written.

Spec: comma-separated items `KIND[:VALUE][@AT]`; AT is seconds after the
first frame and places the fault (a run of consecutive frames for the frame
kinds); without it the faults land at random frames or samples, fixed by the
seed, never in the first second or the last half second (10 % and 5 % of a
shorter recording), and at least three
frames (attitude samples) apart from each other so every one stays countable.

  drop:N          N frames missing: list lines and files left out
  dup:N           N frames listed twice (same stamp, same files)
  swap:N          N pairs of neighbouring frames listed in swapped order
  truncate:N      N colour images cut to half their size
  corrupt:N       N depth images with 64 garbage bytes inside (size and chunk
                  layout kept: only the checksum tells)
  zero-depth:N    N depth images replaced by all-zero images
  att-gap:S       attitude samples missing for S seconds (S > 0.2)
  att-nan:N       N attitude samples written as NaN
  att-spike:N     N attitude samples turned 20-45 deg about a random axis
  clock-jump:S    every stamp after a point moves forward by S seconds (S >= 1)

VALUE defaults to 1 (counts), 0.5 s (att-gap) or 2 s (clock-jump). A clock
jump moves the stamps of every list and text file (colour, depth, ground
truth, attitude...): the recording's one clock jumps. Attitude faults on a
recording without attitude.txt write one from groundtruth.txt first (the
camera orientation, through the mount in camera.toml).

`faults.json` in the copy lists what was done and what the reader should
count on top of the source's own counts (`expected`).
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from onboard import NislamError, __version__

from .outdir import FAULTS_MANIFEST, SIM_MANIFEST, prepare_out_dir
from .tum import CLOCK_JUMP_MIN_S, DEFAULT_GT_MAX_GAP_S, associate, load_camera

log = logging.getLogger(__name__)

FRAME_KINDS = ("drop", "dup", "swap", "truncate", "corrupt", "zero-depth")
SAMPLE_KINDS = ("att-nan", "att-spike")
KINDS = (*FRAME_KINDS, "att-gap", *SAMPLE_KINDS, "clock-jump")
_DEFAULT_VALUE = {"att-gap": 0.5, "clock-jump": 2.0}
START_MARGIN_S = 1.0  # the tracker gets its first key frame in peace
END_MARGIN_S = 0.5
SPACING = 3  # faulted frames (samples) at least this many apart
SPIKE_DEG = (20.0, 45.0)
CORRUPT_OFFSET = 16  # non-PNG files: garbage right after the first header bytes
CORRUPT_BYTES = 64

# What the reader should count per fault (sim_replay.tum.SkipCounts fields).
_EXPECTED: dict[str, dict[str, int]] = {
    "drop": {"dropped_frames": 1},
    "dup": {"duplicate_stamps": 2},  # the colour and the depth entry
    "swap": {"out_of_order_stamps": 2},
    "truncate": {"truncated_files": 1, "unreadable_files": 1},
    "corrupt": {"unreadable_files": 1},
    "zero-depth": {"empty_depth_frames": 1},
    "att-gap": {"attitude_gaps": 1},
    "att-nan": {"attitude_nan_samples": 1},
    "att-spike": {"attitude_spikes": 1},
    "clock-jump": {"clock_jumps": 1},
}


@dataclass(frozen=True)
class FaultItem:
    kind: str
    value: float  # a count, or seconds for att-gap / clock-jump
    at_s: float | None = None

    @property
    def count(self) -> int:
        return 1 if self.kind in ("att-gap", "clock-jump") else int(self.value)

    def text(self) -> str:
        v = f"{int(self.value)}" if self.kind not in _DEFAULT_VALUE else f"{self.value:g}"
        return f"{self.kind}:{v}" + ("" if self.at_s is None else f"@{self.at_s:g}")


def parse_spec(spec: str) -> tuple[FaultItem, ...]:
    """Parse a fault spec (see the module doc); NislamError names a bad item."""
    items = []
    for raw in spec.split(","):
        text = raw.strip()
        if not text:
            continue
        body, _, at_text = text.partition("@")
        kind, _, value_text = body.partition(":")
        kind = kind.strip().lower()
        if kind not in KINDS:
            raise NislamError(f"fault spec: unknown kind {kind!r} in {text!r} "
                              f"(known: {', '.join(KINDS)})")
        try:
            value = float(value_text) if value_text else float(_DEFAULT_VALUE.get(kind, 1))
            at_s = float(at_text) if at_text else None
        except ValueError:
            raise NislamError(f"fault spec: {text!r} is not KIND[:VALUE][@SECONDS]") from None
        if not math.isfinite(value) or (at_s is not None and not (math.isfinite(at_s)
                                                                 and at_s >= 0)):
            raise NislamError(f"fault spec: {text!r}: values must be finite, @ at least 0")
        if kind == "att-gap" and not value > DEFAULT_GT_MAX_GAP_S:
            raise NislamError(f"fault spec: {text!r}: an attitude gap must be longer than "
                              f"{DEFAULT_GT_MAX_GAP_S:g} s (shorter ones are bridged)")
        if kind == "clock-jump" and not value >= CLOCK_JUMP_MIN_S:
            raise NislamError(f"fault spec: {text!r}: a clock jump must be at least "
                              f"{CLOCK_JUMP_MIN_S:g} s (shorter ones read as dropped frames)")
        if kind not in _DEFAULT_VALUE and (value != int(value) or value < 1):
            raise NislamError(f"fault spec: {text!r}: the count must be a whole number >= 1")
        items.append(FaultItem(kind, value, at_s))
    return tuple(items)


# --------------------------------------------------------------------------- lists


@dataclass
class _Row:
    """One line of a list or text file; `stamp` None for comments and lines
    without a leading number (kept as they are)."""

    text: str
    stamp: float | None = None
    stamp_text: str = ""
    file: str = ""

    def shifted(self, dt_s: float) -> "_Row":
        decimals = len(self.stamp_text.partition(".")[2])
        new = f"{self.stamp + dt_s:.{decimals}f}"
        return _Row(new + self.text[len(self.stamp_text):], self.stamp + dt_s, new, self.file)


def _read_rows(path: Path, with_file: bool) -> list[_Row]:
    rows = []
    for line in path.read_text(errors="replace").splitlines():
        s = line.strip()
        parts = s.replace(",", " ").replace("\t", " ").split()
        row = _Row(s)
        if parts and not s.startswith("#"):
            try:
                t = float(parts[0])
            except ValueError:
                t = math.nan
            if math.isfinite(t) and s.startswith(parts[0]) and (len(parts) >= 2 or not with_file):
                row = _Row(s, t, parts[0], parts[1] if with_file else "")
        rows.append(row)
    return rows


def _write_rows(path: Path, rows: list[_Row]) -> None:
    path.write_text("".join(r.text + "\n" for r in rows))


@dataclass
class _Frame:
    """A usable frame of the source: its rows in both lists (row indices)."""

    t_s: float
    rgb_row: int
    depth_row: int


@dataclass
class _Plan:
    drop: set[int] = field(default_factory=set)  # frame indices
    dup: set[int] = field(default_factory=set)
    swap: set[int] = field(default_factory=set)  # first frame of each swapped pair
    truncate: set[int] = field(default_factory=set)
    corrupt: set[int] = field(default_factory=set)
    zero_depth: set[int] = field(default_factory=set)
    att_nan: set[int] = field(default_factory=set)  # attitude row indices
    att_spike: set[int] = field(default_factory=set)
    att_gaps: list[tuple[float, float]] = field(default_factory=list)  # [t0, t1) removed
    jumps: list[tuple[float, float]] = field(default_factory=list)  # (at stamp, +seconds)


# --------------------------------------------------------------------------- inject


def inject_faults(src: Path | str, dst: Path | str, items: tuple[FaultItem, ...] | str,
                  seed: int = 0) -> dict[str, Any]:
    """Write a damaged copy of recording `src` into `dst`; returns the manifest
    (also written to dst/faults.json)."""
    src, dst = Path(src), Path(dst)
    if isinstance(items, str):
        items = parse_spec(items)
    if not (src / "rgb.txt").is_file() or not (src / "depth.txt").is_file():
        raise NislamError(f"{src} is not a TUM-layout recording (no rgb.txt / depth.txt)")
    if dst.resolve() == src.resolve():
        raise NislamError("the damaged copy must go to another folder than its source")
    camera = load_camera(src)
    rgb = _read_rows(src / "rgb.txt", with_file=True)
    depth = _read_rows(src / "depth.txt", with_file=True)
    frames = _usable_frames(src, rgb, depth)
    if len(frames) < 3:
        raise NislamError(f"{src}: too few usable frames ({len(frames)}) to damage")
    att_path = src / "attitude.txt"
    att_source = "attitude.txt"
    needs_att = any(i.kind in ("att-gap", *SAMPLE_KINDS) for i in items)
    att: list[_Row] | None = _read_rows(att_path, with_file=False) if att_path.is_file() else None
    if needs_att and att is None:
        att = _attitude_from_groundtruth(src, camera.q_B_C_xyzw)
        att_source = "groundtruth.txt (camera orientation through the mount)"

    rng = np.random.default_rng([seed, 0xFA17])
    plan = _plan(items, frames, rgb, depth, att, rng)
    prepare_out_dir(dst)
    manifest_faults = _apply(src, dst, plan, items, frames, rgb, depth, att, camera, rng)
    expected: dict[str, int] = {}
    for it in items:
        for key, per in _EXPECTED[it.kind].items():
            expected[key] = expected.get(key, 0) + per * it.count
    manifest = {
        "generator": f"nislam-onboard {__version__} fault injection",
        "source": str(src.resolve()),
        "spec": ",".join(i.text() for i in items),
        "seed": seed,
        "attitude_source": att_source if needs_att else None,
        "faults": manifest_faults,
        "expected": expected,
    }
    (dst / FAULTS_MANIFEST).write_text(json.dumps(manifest, indent=2) + "\n")
    log.info("%s: damaged copy of %s written (%s)", dst, src, manifest["spec"])
    return manifest


def _usable_frames(src: Path, rgb: list[_Row], depth: list[_Row]) -> list[_Frame]:
    """Associated frames whose two files exist, in time order (as the reader pairs them)."""
    rgb_idx = [k for k, r in enumerate(rgb) if r.stamp is not None]
    depth_idx = [k for k, r in enumerate(depth) if r.stamp is not None]
    pairs = associate([(rgb[k].stamp, rgb[k].file) for k in rgb_idx],
                      [(depth[k].stamp, depth[k].file) for k in depth_idx])
    out = []
    for i, j in pairs:
        r, d = rgb_idx[i], depth_idx[j]
        if (src / rgb[r].file).is_file() and (src / depth[d].file).is_file():
            out.append(_Frame(rgb[r].stamp, r, d))
    return out


def _attitude_from_groundtruth(src: Path, q_B_C_xyzw) -> list[_Row]:
    gt_path = src / "groundtruth.txt"
    if not gt_path.is_file():
        raise NislamError(f"{src} has neither attitude.txt nor groundtruth.txt: "
                          "no attitude to damage")
    rows = [_Row("# attitude from groundtruth.txt (nislam fault injection): body in W"),
            _Row("# timestamp qx qy qz qw")]
    r_c_b = Rotation.from_quat(q_B_C_xyzw).inv()
    for row in _read_rows(gt_path, with_file=False):
        parts = row.text.split()
        if row.stamp is None or len(parts) < 8:
            continue
        try:
            q_w_c = Rotation.from_quat([float(v) for v in parts[4:8]])
        except ValueError:
            continue
        q = (q_w_c * r_c_b).as_quat()  # R_W_B = R_W_C R_C_B
        rows.append(_Row(f"{row.stamp_text} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}",
                         row.stamp, row.stamp_text))
    return rows


# --------------------------------------------------------------------------- planning


def _plan(items, frames: list[_Frame], rgb: list[_Row], depth: list[_Row],
          att: list[_Row] | None, rng: np.random.Generator) -> _Plan:
    plan = _Plan()
    t = np.array([f.t_s for f in frames])
    span = t[-1] - t[0]
    # Short recordings (test fixtures) keep proportionate margins.
    lo_t = t[0] + min(START_MARGIN_S, 0.1 * span)
    hi_t = t[-1] - min(END_MARGIN_S, 0.05 * span)
    eligible = set(np.flatnonzero((t >= lo_t) & (t <= hi_t)).tolist())
    taken: set[int] = set()

    def reserve(ks: list[int]) -> None:
        for k in ks:
            taken.update(range(k - SPACING + 1, k + SPACING))

    def free(ks: list[int]) -> bool:
        return all(k in eligible and k not in taken for k in ks)

    def runs(item: FaultItem, width: int, ok) -> list[int]:
        """Start frames of `item.count` faults each `width` frames wide."""
        n = item.count
        if item.at_s is not None:
            k0 = int(np.searchsorted(t, t[0] + item.at_s))
            ks = [k0 + width * j for j in range(n)]
            span = [k for k0_ in ks for k in range(k0_, k0_ + width)]
            if not (free(span) and all(ok(k) for k in ks)):
                raise NislamError(f"fault {item.text()}: frames at {item.at_s:g} s are outside "
                                  f"the recording's margins or too close to another fault")
            taken.update(span)
            reserve([span[0], span[-1]])
            return ks
        chosen = []
        for k in rng.permutation(sorted(eligible)).tolist():
            span = list(range(k, k + width))
            if len(chosen) < n and free(span) and ok(k):
                chosen.append(k)
                reserve(span)
        if len(chosen) < n:
            raise NislamError(f"fault {item.text()}: the recording has room for only "
                              f"{len(chosen)} such faults (after the others)")
        return chosen

    def adjacent(k: int) -> bool:
        """Frames k and k+1 are neighbouring entries in both lists (swap)."""
        if k + 1 >= len(frames):
            return False
        a, b = frames[k], frames[k + 1]
        return (_next_entry(rgb, a.rgb_row) == b.rgb_row
                and _next_entry(depth, a.depth_row) == b.depth_row)

    for it in items:  # clock jumps first: the frames around a jump stay clean
        if it.kind == "clock-jump":
            k = runs(it, 2, lambda k: True)[0]
            # The jump falls between frame k and k+1.
            plan.jumps.append((0.5 * (t[k] + t[k + 1]), it.value))
    for it in items:
        if it.kind in FRAME_KINDS:
            width = 2 if it.kind == "swap" else 1
            ks = runs(it, width, adjacent if it.kind == "swap" else (lambda k: True))
            getattr(plan, it.kind.replace("-", "_")).update(ks)
    if att is not None:
        _plan_attitude(items, plan, att, (lo_t, hi_t), rng)
    return plan


def _next_entry(rows: list[_Row], k: int) -> int | None:
    for j in range(k + 1, len(rows)):
        if rows[j].stamp is not None:
            return j
    return None


def _plan_attitude(items, plan: _Plan, att: list[_Row], window: tuple[float, float],
                   rng: np.random.Generator) -> None:
    idx = np.array([k for k, r in enumerate(att) if r.stamp is not None])
    if len(idx) == 0:
        raise NislamError("attitude: no sample to damage")
    ts = np.array([att[k].stamp for k in idx])
    blocked = np.zeros(len(idx), dtype=bool)  # samples near another fault
    # Nothing in the frame margins, nor right at a clock jump.
    blocked |= (ts < window[0]) | (ts > window[1])
    for t_j, _dt in plan.jumps:
        blocked |= np.abs(ts - t_j) < 0.2
    for it in items:
        if it.kind != "att-gap":
            continue
        t0 = ts[0] + it.at_s if it.at_s is not None else None
        if t0 is None:
            # Random start with the whole gap (and a margin) clear of other faults.
            starts = rng.permutation(np.flatnonzero(~blocked)).tolist()
            for s in starts:
                t_try = ts[s]
                inside = (ts >= t_try - 0.1) & (ts < t_try + it.value + 0.1)
                if not blocked[inside].any() and t_try + it.value < window[1]:
                    t0 = float(t_try)
                    break
            if t0 is None:
                raise NislamError(f"fault {it.text()}: no room for the gap in the recording")
        inside = (ts >= t0 - 0.1) & (ts < t0 + it.value + 0.1)
        if blocked[inside].any():
            raise NislamError(f"fault {it.text()}: the gap overlaps a margin or another fault")
        blocked |= inside
        plan.att_gaps.append((t0, t0 + it.value))
    for it in items:
        if it.kind not in SAMPLE_KINDS:
            continue
        chosen = []
        candidates = (np.flatnonzero(~blocked) if it.at_s is None
                      else np.flatnonzero(ts >= ts[0] + it.at_s)[:1])
        order = rng.permutation(candidates) if it.at_s is None else candidates
        for s in order.tolist():
            if len(chosen) == it.count:
                break
            lo, hi = max(s - SPACING + 1, 0), min(s + SPACING, len(ts))
            if blocked[lo:hi].any():
                continue
            chosen.append(s)
            blocked[lo:hi] = True
        if it.at_s is not None and it.count > 1:
            raise NislamError(f"fault {it.text()}: @ places a single sample; "
                              f"give several items for more")
        if len(chosen) < it.count:
            raise NislamError(f"fault {it.text()}: room for only {len(chosen)} such samples")
        target = plan.att_nan if it.kind == "att-nan" else plan.att_spike
        target.update(int(idx[s]) for s in chosen)


# --------------------------------------------------------------------------- writing


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


def _apply(src: Path, dst: Path, plan: _Plan, items, frames: list[_Frame], rgb: list[_Row],
           depth: list[_Row], att: list[_Row] | None, camera, rng: np.random.Generator
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


def _apply_lists(dst: Path, plan: _Plan, frames: list[_Frame], rgb: list[_Row],
                 depth: list[_Row], record: _Record) -> tuple[list[_Row], list[_Row]]:
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
    _write_rows(dst / "rgb.txt", out[0])
    _write_rows(dst / "depth.txt", out[1])
    return out[0], out[1]


def _damaged_images(src: Path, plan: _Plan, frames: list[_Frame], rgb: list[_Row],
                    depth: list[_Row], camera, rng: np.random.Generator, record: _Record
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


def _apply_attitude(dst: Path, plan: _Plan, att: list[_Row], rng: np.random.Generator,
                    record: _Record) -> None:
    """attitude.txt with gaps cut out, NaN and spike samples."""
    out = []
    for k, row in enumerate(att):
        if row.stamp is not None and any(a <= row.stamp < b for a, b in plan.att_gaps):
            continue
        if k in plan.att_nan:
            row = _Row(f"{row.stamp_text} nan nan nan nan", row.stamp, row.stamp_text)
            record.note("att-nan", row.stamp)
        elif k in plan.att_spike:
            row = _spike(row, rng)
            record.note("att-spike", row.stamp)
        out.append(_shift_row(row, plan.jumps))
    _write_rows(dst / "attitude.txt", out)
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


def _edit_list(rows: list[_Row], drop: set[int], dup: set[int], swap: dict[int, int],
               jumps: list[tuple[float, float]]) -> list[_Row]:
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


def _shift_row(row: _Row, jumps: list[tuple[float, float]]) -> _Row:
    if row.stamp is None:
        return row
    dt = sum(d for t_j, d in jumps if row.stamp >= t_j)
    return row.shifted(dt) if dt else row


def _spike(row: _Row, rng: np.random.Generator) -> _Row:
    parts = row.text.split()
    try:
        q = Rotation.from_quat([float(v) for v in parts[1:5]])
    except (ValueError, IndexError):
        return row
    axis = rng.standard_normal(3)
    angle = math.radians(rng.uniform(*SPIKE_DEG))
    qs = (q * Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle)).as_quat()
    return _Row(f"{row.stamp_text} {qs[0]:.9f} {qs[1]:.9f} {qs[2]:.9f} {qs[3]:.9f}",
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
            _write_rows(dst / p.name, [_shift_row(r, jumps)
                                       for r in _read_rows(p, with_file=False)])
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
