"""The per-frame error budget of NI-SLAM on synthetic flights: render a flight
with one camera error source switched on, replay it with one attitude error
or tracker setting, and split the per-frame error (docs/nislam-error-budget.md;
`scripts/error_budget.py` prints the table).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from onboard.core.evaluation import evaluate, ground_truth_at
from onboard.core.messages import TrackResult
from onboard.core.trajectory import Trajectory
from onboard.nislam.params import NislamParams
from onboard.nislam.tracker import NislamTracker
from sim_replay.attitude import AttitudeErrorModel, attitude_for_replay
from sim_replay.sensors import PERFECT_DEPTH, DepthSensorModel
from sim_replay.sim import SimOptions, simulate
from sim_replay.tum import open_sequence

_NOISE_ONLY = dataclasses.replace(PERFECT_DEPTH, sigma_m_per_m2=DepthSensorModel.sigma_m_per_m2)

# Camera models (rendered): name -> SimOptions fields.
CAMERAS: dict[str, dict[str, Any]] = {
    "ideal": {"depth": PERFECT_DEPTH, "pixel_noise_dn": 0.0},
    "pixel-noise": {"depth": PERFECT_DEPTH, "pixel_noise_dn": 2.0},
    "depth-noise": {"depth": _NOISE_ONLY, "pixel_noise_dn": 0.0},
    "depth-holes": {"depth": DepthSensorModel(sigma_m_per_m2=0.0), "pixel_noise_dn": 0.0},
    "coarse-texture": {"depth": PERFECT_DEPTH, "pixel_noise_dn": 0.0, "texel_m": 0.012},
    "camera": {},  # the default sensor model: noise, holes and 3 mm texels at once
}

# Sources: name -> (camera, attitude error fields, [nislam] overrides).
SOURCES: dict[str, tuple[str, dict[str, Any], dict[str, Any]]] = {
    "none (ideal camera, exact attitude)": ("ideal", {}, {}),
    "t_z: tilt fit on (before)": ("ideal", {}, {"depth_tilt_fit": True}),
    "t_z: inverse-variance weights, sub-cell": ("ideal", {}, {"depth_sigma_floor_m": 0.001}),
    "no time-offset calibration": ("ideal", {}, {"calibrate_time_offset": False}),
    "pixel noise 2 DN": ("pixel-noise", {}, {}),
    "depth noise 0.0015 z^2": ("depth-noise", {}, {}),
    "depth holes (range, edges)": ("depth-holes", {}, {}),
    "texture 12 mm texels": ("coarse-texture", {}, {}),
    "attitude noise 0.1 deg": ("ideal", {"noise_deg": 0.1}, {}),
    "attitude noise 1 deg": ("ideal", {"noise_deg": 1.0}, {}),
    "attitude offset 10 ms": ("ideal", {"offset_ms": 10.0}, {}),
    "camera model (all camera sources)": ("camera", {}, {}),
    "camera model, tilt fit on (before)": ("camera", {}, {"depth_tilt_fit": True}),
    "camera model, weights, sub-cell": ("camera", {}, {"depth_sigma_floor_m": 0.001}),
}


def render_flight(scenario: str, camera: str, seconds: float, seed: int, work: Path) -> Path:
    """The flight rendered with camera model `camera` into `work` (kept: the
    same seed writes the same bytes, so a second call re-uses it)."""
    out = Path(work) / f"{scenario}_{camera}_{seconds:g}s_seed{seed}"
    if not (out / "sim.json").exists():
        simulate(scenario, out, SimOptions(seconds=seconds, seed=seed, **CAMERAS[camera]),
                 progress=False)
    return out


class KeyTimes(dict):
    """Each NI-SLAM key's id -> the time of the frame it was made from, read
    off the results in order: the frame that announces it (`new_keyframe`),
    or the last trusted frame before one that no longer matched its key at
    all (`keyframe_from_previous`)."""

    def __init__(self) -> None:
        super().__init__()
        self._last_trusted_t: float | None = None

    def add(self, r: TrackResult) -> None:
        if r.keyframe_from_previous and self._last_trusted_t is not None:
            self[r.reference_keyframe_id if r.trusted else r.keyframe_id] = self._last_trusted_t
        if r.new_keyframe:
            self[r.keyframe_id] = r.t_s
        if r.trusted:
            self._last_trusted_t = r.t_s


def score_flight(
    seq_dir: Path, attitude: dict[str, Any] | None = None, nislam: dict[str, Any] | None = None,
    seed: int = 0, max_frames: int | None = None,
) -> dict[str, Any]:
    """Replay `seq_dir` with NI-SLAM (`nislam` overriding NislamParams, the
    `attitude` fields of AttitudeErrorModel applied to the recorded attitude)
    and return the budget's columns:

    rpe1 / rpe10: translational RPE over 1 / 10 frames (RMSE, m); lat / ax: the
    lag-1 error of frames matched against the same key, split into the key's
    lateral axes (the correlation peak, Eqs. 14-15) and its optical axis (the
    depth translation, Eq. 18): the increment t = (-du s, -dv s, t_z) against
    the key is compared with the true motion since the key's frame in the key's
    true axes, so these do not depend on where the key itself was put; jump:
    median lag-1 error across a key change; ate, ratio (path length), tracked
    share, keys (new / changes), res_mm (median cell size).
    """
    params = dataclasses.replace(NislamParams(), **(nislam or {}))
    errors = AttitudeErrorModel(**{"seed": seed, **(attitude or {})})
    seq = open_sequence(seq_dir, 0.02, True)
    att, _ = attitude_for_replay(seq, errors, 0.2)
    tracker = NislamTracker(seq.intrinsics, params)
    rows = []
    key_t = KeyTimes()
    for k, frame in enumerate(seq.frames()):
        if max_frames is not None and k >= max_frames:
            break
        r = tracker.track(frame, att)
        key_t.add(r)
        if r.trusted:
            rows.append(r)
    t = np.array([r.t_s for r in rows])
    est = Trajectory(t, np.array([r.p_W_m for r in rows]).reshape(-1, 3),
                     np.array([r.q_W_C_xyzw for r in rows]).reshape(-1, 4))
    gt, valid = ground_truth_at(t, seq.groundtruth, 0.2)
    est = est.slice_valid(valid)
    rows = [r for r, ok in zip(rows, valid) if ok]
    ref = np.array([r.reference_keyframe_id for r in rows])
    m = evaluate(est, gt, reference_keyframe_id=ref)
    inc_err = np.full((len(rows), 3), np.nan)
    t_key = np.array([key_t.get(int(k), np.nan) for k in ref])
    idx = np.flatnonzero(np.isfinite(t_key))
    p_k, q_k, v_k = seq.groundtruth.interpolate(t_key[idx], 0.2)
    for n, i in enumerate(idx):
        if v_k[n]:
            r = rows[i]
            meas = np.array([-r.shift_cells[0] * r.res_m, -r.shift_cells[1] * r.res_m, r.tz_m])
            inc_err[i] = meas - Rotation.from_quat(q_k[n]).inv().apply(gt.p_xyz_m[i] - p_k[n])
    same = np.zeros(len(rows), bool)
    same[1:] = ref[1:] == ref[:-1]
    d = np.diff(inc_err, axis=0, prepend=np.nan)[same]
    d = d[np.isfinite(d).all(axis=1)]
    new = sum(r.keyframes_added for r in rows)
    return {
        "rpe1": m.rpe_lag1_m, "rpe3": m.rpe_lag3_m, "rpe10": m.rpe_lag10_m, "rpe30": m.rpe_lag30_m,
        "lat": float(np.sqrt(np.mean(np.sum(d[:, :2] ** 2, axis=1)))) if len(d) else float("nan"),
        "ax": float(np.sqrt(np.mean(d[:, 2] ** 2))) if len(d) else float("nan"),
        "jump": m.keyframe_jump_median_m, "ate": m.ate_rmse_m, "ratio": m.path_length_ratio,
        "tracked": len(rows) / max(min(len(seq), max_frames or len(seq)), 1), "keys": f"{new}/{m.keyframe_changes}",
        "res_mm": float(np.median([r.res_m for r in rows])) * 1e3,
        "arrays": {"t_s": est.t_s, "increment_error_m": inc_err, "same_key": same,
                   "reference_keyframe_id": ref, "res_m": np.array([r.res_m for r in rows]),
                   "shift_cells": np.array([r.shift_cells for r in rows]).reshape(-1, 2),
                   "tz_m": np.array([r.tz_m for r in rows])},
    }
