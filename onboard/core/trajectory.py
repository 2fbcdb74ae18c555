"""Timestamped rigid-body trajectories: interpolation and TUM text I/O.

Pure numpy/scipy; no logging setup, no threads.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation


@dataclass(frozen=True)
class Trajectory:
    """Poses T_W_X at times: position `p_xyz_m` (N,3) and orientation `q_xyzw` (N,4).

    Times are strictly increasing seconds on the recording's clock.
    """

    t_s: np.ndarray
    p_xyz_m: np.ndarray
    q_xyzw: np.ndarray

    def __post_init__(self) -> None:
        if not (len(self.t_s) == len(self.p_xyz_m) == len(self.q_xyzw)):
            raise ValueError("trajectory arrays differ in length")

    def __len__(self) -> int:
        return len(self.t_s)

    @classmethod
    def from_samples(cls, t_s, p_xyz_m, q_xyzw) -> "Trajectory":
        """Build from unsorted samples: sorts by time, drops duplicate times and
        non-finite or zero-norm quaternions, normalises quaternions."""
        t = np.asarray(t_s, dtype=np.float64)
        p = np.asarray(p_xyz_m, dtype=np.float64).reshape(-1, 3)
        q = np.asarray(q_xyzw, dtype=np.float64).reshape(-1, 4)
        norm = np.linalg.norm(q, axis=1)
        ok = np.isfinite(t) & np.isfinite(p).all(axis=1) & np.isfinite(q).all(axis=1) & (norm > 1e-6)
        t, p, q, norm = t[ok], p[ok], q[ok], norm[ok]
        order = np.argsort(t, kind="stable")
        t, p, q, norm = t[order], p[order], q[order], norm[order]
        keep = np.ones(len(t), dtype=bool)
        keep[1:] = np.diff(t) > 0
        return cls(t[keep], p[keep], q[keep] / norm[keep, None])

    def interpolate(self, t_query_s, max_gap_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Poses at `t_query_s`: linear position, slerp rotation.

        Never extrapolates: a query outside [t0, tN] or inside a gap between two
        samples longer than `max_gap_s` is invalid. Returns (p (M,3), q_xyzw (M,4),
        valid (M,) bool); invalid rows are NaN.
        """
        tq = np.atleast_1d(np.asarray(t_query_s, dtype=np.float64))
        m = len(tq)
        p_out = np.full((m, 3), np.nan)
        q_out = np.full((m, 4), np.nan)
        valid = np.zeros(m, dtype=bool)
        if len(self.t_s) < 2:
            if len(self.t_s) == 1:
                hit = tq == self.t_s[0]
                p_out[hit], q_out[hit], valid[hit] = self.p_xyz_m[0], self.q_xyzw[0], True
            return p_out, q_out, valid
        i = np.searchsorted(self.t_s, tq, side="right")
        inside = (tq >= self.t_s[0]) & (tq <= self.t_s[-1])
        i = np.clip(i, 1, len(self.t_s) - 1)
        gap = self.t_s[i] - self.t_s[i - 1]
        # A query on a sample's own stamp is that sample, whatever gap follows.
        on_sample = (tq == self.t_s[i - 1]) | (tq == self.t_s[i])
        valid = inside & ((gap <= max_gap_s + 1e-9) | on_sample)
        if not valid.any():
            return p_out, q_out, valid
        iv = i[valid]
        t0, t1 = self.t_s[iv - 1], self.t_s[iv]
        w = ((tq[valid] - t0) / (t1 - t0))[:, None]
        p_out[valid] = (1.0 - w) * self.p_xyz_m[iv - 1] + w * self.p_xyz_m[iv]
        q_out[valid] = _slerp_pairs(self.q_xyzw[iv - 1], self.q_xyzw[iv], w[:, 0])
        return p_out, q_out, valid

    def slice_valid(self, mask: np.ndarray) -> "Trajectory":
        return Trajectory(self.t_s[mask], self.p_xyz_m[mask], self.q_xyzw[mask])


def _slerp_pairs(q0_xyzw: np.ndarray, q1_xyzw: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Row-wise slerp between unit quaternions q0 and q1 at fractions w."""
    r0 = Rotation.from_quat(q0_xyzw)
    delta = (r0.inv() * Rotation.from_quat(q1_xyzw)).as_rotvec()
    return (r0 * Rotation.from_rotvec(delta * w[:, None])).as_quat()


def read_tum(path: Path | str) -> Trajectory:
    """Read `timestamp tx ty tz qx qy qz qw` lines; '#' comments and malformed
    lines are skipped (counted by callers that care via `parse_tum_lines`)."""
    traj, _bad = parse_tum_lines(Path(path).read_text(errors="replace").splitlines())
    return traj


def parse_tum_lines(lines: list[str]) -> tuple[Trajectory, int]:
    """Parse TUM trajectory lines; returns the trajectory and the count of
    malformed (non-comment) lines that were skipped."""
    rows: list[list[float]] = []
    bad = 0
    for line in lines:
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split()
        try:
            vals = [float(v) for v in parts[:8]]
        except ValueError:
            bad += 1
            continue
        if len(vals) != 8 or not np.all(np.isfinite(vals)):
            bad += 1
            continue
        rows.append(vals)
    if not rows:
        empty = np.zeros((0,))
        return Trajectory(empty, np.zeros((0, 3)), np.zeros((0, 4))), bad
    a = np.asarray(rows)
    return Trajectory.from_samples(a[:, 0], a[:, 1:4], a[:, 4:8]), bad


def write_tum(path: Path | str, t_s, p_xyz_m, q_xyzw) -> None:
    """Write a TUM trajectory file (what `evo` reads), atomically."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw\n")
        for t, p, q in zip(t_s, p_xyz_m, q_xyzw):
            f.write(
                f"{t:.6f} {p[0]:.6f} {p[1]:.6f} {p[2]:.6f} "
                f"{q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}\n"
            )
    tmp.replace(path)
