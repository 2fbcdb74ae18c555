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
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from onboard import NislamError, __version__
from sim_replay.fault_plan import (
    EXPECTED,
    SAMPLE_KINDS,
    FaultItem,
    Row,
    parse_spec,
    plan_faults,
    read_rows,
    usable_frames,
)
from sim_replay.fault_writer import apply_plan
from sim_replay.outdir import FAULTS_MANIFEST, finish_out_dir, prepare_out_dir
from sim_replay.tum_files import load_camera

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- lists


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
    rgb = read_rows(src / "rgb.txt", with_file=True)
    depth = read_rows(src / "depth.txt", with_file=True)
    frames = usable_frames(src, rgb, depth)
    if len(frames) < 3:
        raise NislamError(f"{src}: too few usable frames ({len(frames)}) to damage")
    att_path = src / "attitude.txt"
    att_source = "attitude.txt"
    needs_att = any(i.kind in ("att-gap", *SAMPLE_KINDS) for i in items)
    att: list[Row] | None = read_rows(att_path, with_file=False) if att_path.is_file() else None
    if needs_att and att is None:
        att = _attitude_from_groundtruth(src, camera.q_B_C_xyzw)
        att_source = "groundtruth.txt (camera orientation through the mount)"

    rng = np.random.default_rng([seed, 0xFA17])
    plan = plan_faults(items, frames, rgb, depth, att, rng)
    prepare_out_dir(dst)
    manifest_faults = apply_plan(src, dst, plan, items, frames, rgb, depth, att, camera, rng)
    expected: dict[str, int] = {}
    for it in items:
        for key, per in EXPECTED[it.kind].items():
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
    finish_out_dir(dst)
    log.info("%s: damaged copy of %s written (%s)", dst, src, manifest["spec"])
    return manifest


def _attitude_from_groundtruth(src: Path, q_B_C_xyzw) -> list[Row]:
    gt_path = src / "groundtruth.txt"
    if not gt_path.is_file():
        raise NislamError(f"{src} has neither attitude.txt nor groundtruth.txt: "
                          "no attitude to damage")
    rows = [Row("# attitude from groundtruth.txt (nislam fault injection): body in W"),
            Row("# timestamp qx qy qz qw")]
    r_c_b = Rotation.from_quat(q_B_C_xyzw).inv()
    for row in read_rows(gt_path, with_file=False):
        parts = row.text.split()
        if row.stamp is None or len(parts) < 8:
            continue
        try:
            q_w_c = Rotation.from_quat([float(v) for v in parts[4:8]])
        except ValueError:
            continue
        q = (q_w_c * r_c_b).as_quat()  # R_W_B = R_W_C R_C_B
        rows.append(Row(f"{row.stamp_text} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}",
                         row.stamp, row.stamp_text))
    return rows


# --------------------------------------------------------------------------- planning


# --------------------------------------------------------------------------- writing


