"""The trajectory plot of a replay: estimate against ground truth, top view,
with the error over time (ATE, and the per-frame error when given) and the
key-frame changes marked.
"""

from __future__ import annotations

import logging
import os
import tempfile
from pathlib import Path

import numpy as np

from onboard.core.evaluation import rmse

log = logging.getLogger(__name__)


_AXIS_NAMES = ("x", "y", "z")


def _plot_axes(xyz: np.ndarray) -> tuple[int, int]:
    """The two axes with the largest extent, in index order: a camera-frame
    trajectory (y down) is flat in x-z, not x-y."""
    extent = np.ptp(xyz, axis=0) if len(xyz) else np.zeros(3)
    a, b = sorted(np.argsort(extent)[-2:].tolist())
    return int(a), int(b)


def plot_trajectory(
    path_png: Path | str,
    estimate_aligned_xyz: np.ndarray,
    gt_xyz: np.ndarray,
    t_s: np.ndarray,
    errors_m: np.ndarray,
    title: str,
    step_errors_m: np.ndarray | None = None,
    key_change: np.ndarray | None = None,
) -> bool:
    """Top view of the aligned estimate against ground truth plus ATE over time;
    with `step_errors_m` (per row, the lag-1 RPE) a panel of the per-frame error,
    with `key_change` (per row, bool) the key-frame changes as vertical lines on
    the error panels and dots on the estimate.

    Returns False if matplotlib is not installed (it is an optional extra).
    """
    try:
        import matplotlib

        matplotlib.use("Agg")  # headless; no display on the vehicle or in CI
        from matplotlib.figure import Figure
    except ImportError:
        log.info("matplotlib not importable; skipping plot %s", path_png)
        return False

    est = np.asarray(estimate_aligned_xyz, dtype=np.float64).reshape(-1, 3)
    gt = np.asarray(gt_xyz, dtype=np.float64).reshape(-1, 3)
    t = np.asarray(t_s, dtype=np.float64)
    err = np.asarray(errors_m, dtype=np.float64)
    a, b = _plot_axes(gt if len(gt) else est)

    # Figure() without pyplot: no global figure registry, safe off the main thread.
    change = (np.zeros(len(t), dtype=bool) if key_change is None
              else np.asarray(key_change, dtype=bool).reshape(-1))
    fig = Figure(figsize=(8, 12 if step_errors_m is not None else 10), layout="constrained")
    if step_errors_m is None:
        ax_top, ax_err = fig.subplots(2, 1, height_ratios=[3, 1])
        ax_step = None
    else:
        ax_top, ax_err, ax_step = fig.subplots(3, 1, height_ratios=[3, 1, 1])
    ax_top.plot(gt[:, a], gt[:, b], color="0.3", lw=1.5, label="ground truth")
    ax_top.plot(est[:, a], est[:, b], color="tab:red", lw=1.0, label="estimate (SE(3)-aligned)")
    if change.any():
        ax_top.plot(est[change, a], est[change, b], ".", color="tab:blue", ms=4,
                    label=f"key-frame change ({int(change.sum())})")
    if len(gt):
        ax_top.plot(gt[0, a], gt[0, b], "o", color="0.3", label="start")
    ax_top.set_xlabel(f"{_AXIS_NAMES[a]} [m]")
    ax_top.set_ylabel(f"{_AXIS_NAMES[b]} [m]")
    ax_top.set_aspect("equal", adjustable="datalim")
    ax_top.set_title(f"{title}\n{_AXIS_NAMES[a]}-{_AXIS_NAMES[b]} plane")
    ax_top.legend(loc="best")
    ax_top.grid(True, alpha=0.3)

    t_rel_s = t - t[0] if len(t) else t
    ax_err.plot(t_rel_s, err, color="tab:red", lw=1.0)
    if len(err):
        rmse_m = rmse(err)
        ax_err.axhline(rmse_m, color="k", ls="--", lw=0.8, label=f"RMSE {rmse_m:.3f} m")
        ax_err.legend(loc="upper left")
    ax_err.set_xlabel("time [s]")
    ax_err.set_ylabel("ATE [m]")
    ax_err.grid(True, alpha=0.3)
    if ax_step is not None:
        step_mm = np.asarray(step_errors_m, dtype=np.float64).reshape(-1) * 1e3
        ax_step.plot(t_rel_s, step_mm, color="tab:red", lw=0.8)
        ax_step.set_xlabel("time [s]")
        ax_step.set_ylabel("per-frame error [mm]")
        ax_step.grid(True, alpha=0.3)
    for ax in (ax_err, ax_step):
        if ax is not None and change.any():
            # One collection, not a line per change: hundreds of keys stay cheap.
            ax.vlines(t_rel_s[change], 0.0, 1.0, transform=ax.get_xaxis_transform(),
                      color="tab:blue", lw=0.5, alpha=0.5, label="key-frame change")

    path = Path(path_png)
    # Temp file then rename so a watcher never picks up a half-written PNG.
    fd, tmp_name = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            fig.savefig(f, format="png", dpi=110)
        os.replace(tmp_name, path)
    except BaseException:
        Path(tmp_name).unlink(missing_ok=True)
        raise
    return True
