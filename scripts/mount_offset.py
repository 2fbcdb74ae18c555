"""A fixed AHRS-to-camera mount rotation, measured two ways on one sequence
(a script, not a test; docs/nislam-error-budget.md, "`tum_fr1_rpy`'s attitude
is off its camera").

    python scripts/mount_offset.py SEQ_DIR [--correct-deg=X,Y,Z ...] [--fit] [--inject-deg=X,Y,Z]

--correct-deg: replay NI-SLAM with every attitude post-multiplied by the
rotation with these XYZ Euler angles (the camera's axes; a mount error R_m is
undone by R_m^T), one replay per triple, and print ATE and RPE.
--fit: replay once with the residual rotation (calibration.RotationResidual)
measured on every frame and fit the mount rotation m to it by least squares,
theta_xy = [(I - R_rel) m]_xy, with R_rel the key-to-frame rotation the frame
was projected with; prints m and its standard error (deg).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import onboard.nislam.tracker as tracker_mod  # noqa: E402
import sim_replay.budget as budget  # noqa: E402
from onboard.nislam.calibration import OffsetCalibration  # noqa: E402


class _Corrected:
    """An attitude source whose rotations are post-multiplied by `r`."""

    def __init__(self, source, r: np.ndarray):
        self.source, self.r = source, r

    def rotation_at(self, t_s: float):
        R = self.source.rotation_at(t_s)
        return None if R is None else R @ self.r

    def __getattr__(self, name):
        return getattr(self.source, name)


def _replay(seq: Path, r: np.ndarray, nislam: dict | None = None) -> dict:
    original = budget.attitude_for_replay

    def corrected(*a, **k):
        att, label = original(*a, **k)
        return _Corrected(att, r), label

    budget.attitude_for_replay = corrected
    try:
        return budget.score_flight(seq, nislam=nislam)
    finally:
        budget.attitude_for_replay = original


def _fit(seq: Path, inject: np.ndarray) -> tuple[np.ndarray, np.ndarray, int, dict]:
    """m [rad] fitted to every frame's residual rotation (the attitude
    post-multiplied by `inject` first), its standard error, the frames used,
    and the replay's scores."""
    rel: dict[int, np.ndarray] = {}
    rows: list[tuple[np.ndarray, np.ndarray]] = []
    project, fit_residual, min_g2 = (tracker_mod.project, tracker_mod.NislamTracker._fit_residual,
                                     OffsetCalibration.MIN_G2)

    def recording_project(cloud, r_rel, *a, **k):
        img = project(cloud, r_rel, *a, **k)
        rel[id(img)] = r_rel
        return img

    def recording_fit(self, key, img, peak, tz_m, g, theta_out):
        theta = key.layers.residual(img, (peak.du_cells, peak.dv_cells), tz_m, self.p)
        if theta is not None and id(img) in rel:
            rows.append((rel[id(img)], theta[:2].copy()))
        return fit_residual(self, key, img, peak, tz_m, g, theta_out)

    tracker_mod.project, tracker_mod.NislamTracker._fit_residual = recording_project, recording_fit
    OffsetCalibration.MIN_G2 = 0.0  # a residual on every frame, not only where it tells time
    try:
        scores = _replay(seq, inject, {"calibrate_every_n_frames": 1})
    finally:
        tracker_mod.project, tracker_mod.NislamTracker._fit_residual = project, fit_residual
        OffsetCalibration.MIN_G2 = min_g2
    a = np.concatenate([(np.eye(3) - r)[:2] for r, _ in rows])
    theta = np.concatenate([t for _, t in rows])
    m, *_ = np.linalg.lstsq(a, theta, rcond=None)
    res = theta - a @ m
    cov = np.linalg.inv(a.T @ a) * float(np.mean(res**2))
    return m, np.sqrt(np.diag(cov)), len(rows), scores


def _rotation(text: str) -> np.ndarray:
    return Rotation.from_euler("xyz", [float(x) for x in text.split(",")], degrees=True).as_matrix()


def _line(label: str, s: dict) -> str:
    rpe = " / ".join(f"{s[k] * 1e3:.2f}" for k in ("rpe1", "rpe3", "rpe10", "rpe30"))
    return (f"{label}: ATE {s['ate'] * 1e3:.2f} mm, RPE 1/3/10/30 {rpe} mm, "
            f"path {s['ratio']:.3f}, tracked {s['tracked'] * 100:.1f} %")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("seq", type=Path)
    ap.add_argument("--correct-deg", action="append", default=[], metavar="X,Y,Z",
                    help="repeatable; write --correct-deg=-1.5,0,0 for a leading minus")
    ap.add_argument("--fit", action="store_true")
    ap.add_argument("--inject-deg", default="0,0,0", metavar="X,Y,Z",
                    help="a known mount error put on every attitude first (a flight has none)")
    args = ap.parse_args()
    inject = _rotation(args.inject_deg)
    if args.fit:
        m, sd, n, scores = _fit(args.seq, inject)
        print(f"residual fit over {n} frames: m = {np.degrees(m).round(3)} deg "
              f"+- {np.degrees(sd).round(3)}")
        print(_line("  (that replay, uncorrected)", scores))
    for text in args.correct_deg:
        print(_line(f"corrected by {text} deg", _replay(args.seq, inject @ _rotation(text))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
