"""Which faults go where: the spec (`KIND[:VALUE][@AT]`), the recording's rows,
and the plan of damaged frames and samples, fixed by the seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from onboard import NislamError
from sim_replay.tum_files import CLOCK_JUMP_MIN_S, DEFAULT_GT_MAX_GAP_S, associate

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
EXPECTED: dict[str, dict[str, int]] = {
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


@dataclass
class Row:
    """One line of a list or text file; `stamp` None for comments and lines
    without a leading number (kept as they are)."""

    text: str
    stamp: float | None = None
    stamp_text: str = ""
    file: str = ""

    def shifted(self, dt_s: float) -> "Row":
        decimals = len(self.stamp_text.partition(".")[2])
        new = f"{self.stamp + dt_s:.{decimals}f}"
        return Row(new + self.text[len(self.stamp_text):], self.stamp + dt_s, new, self.file)


def read_rows(path: Path, with_file: bool) -> list[Row]:
    rows = []
    for line in path.read_text(errors="replace").splitlines():
        s = line.strip()
        parts = s.replace(",", " ").replace("\t", " ").split()
        row = Row(s)
        if parts and not s.startswith("#"):
            try:
                t = float(parts[0])
            except ValueError:
                t = math.nan
            if math.isfinite(t) and s.startswith(parts[0]) and (len(parts) >= 2 or not with_file):
                row = Row(s, t, parts[0], parts[1] if with_file else "")
        rows.append(row)
    return rows


def write_rows(path: Path, rows: list[Row]) -> None:
    path.write_text("".join(r.text + "\n" for r in rows))


@dataclass
class Frame:
    """A usable frame of the source: its rows in both lists (row indices)."""

    t_s: float
    rgb_row: int
    depth_row: int


@dataclass
class Plan:
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


def usable_frames(src: Path, rgb: list[Row], depth: list[Row]) -> list[Frame]:
    """Associated frames whose two files exist, in time order (as the reader pairs them)."""
    rgb_idx = [k for k, r in enumerate(rgb) if r.stamp is not None]
    depth_idx = [k for k, r in enumerate(depth) if r.stamp is not None]
    pairs = associate([(rgb[k].stamp, rgb[k].file) for k in rgb_idx],
                      [(depth[k].stamp, depth[k].file) for k in depth_idx])
    out = []
    for i, j in pairs:
        r, d = rgb_idx[i], depth_idx[j]
        if (src / rgb[r].file).is_file() and (src / depth[d].file).is_file():
            out.append(Frame(rgb[r].stamp, r, d))
    return out


def plan_faults(items, frames: list[Frame], rgb: list[Row], depth: list[Row],
          att: list[Row] | None, rng: np.random.Generator) -> Plan:
    plan = Plan()
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


def _next_entry(rows: list[Row], k: int) -> int | None:
    for j in range(k + 1, len(rows)):
        if rows[j].stamp is not None:
            return j
    return None


def _plan_attitude(items, plan: Plan, att: list[Row], window: tuple[float, float],
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
