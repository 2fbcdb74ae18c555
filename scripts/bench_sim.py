"""Rendering speed of the synthetic flights on one core.

    .venv/bin/python scripts/bench_sim.py [SCENARIO ...] [--seconds N] [--width PX --height PX]

Renders every frame of each flight twice: once to build every texture the
flight sees (a start-up cost), then timed, with OpenCV on one thread. Reports
the median and p95 per frame of the renderer alone and with the depth and
colour sensor models, as CPU time of the rendering thread (what one core of
the companion computer would spend, whatever else this machine runs) and as
wall time. PNG writing is not included: `nislam sim` does it on another thread.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from onboard.core.rotations import mount_rotation
from sim_replay.flights import SCENARIOS, Flight, scenario  # noqa: E402
from sim_replay.render import Renderer  # noqa: E402
from sim_replay.scene import make_scene  # noqa: E402
from sim_replay.sensors import ColourNoise, depth_to_png_units, measure_depth
from sim_replay.sim import SimOptions  # noqa: E402


def bench(name: str, opts: SimOptions) -> dict[str, list[float]]:
    scen = scenario(name)
    renderer = Renderer(make_scene(scen.scene), opts.intrinsics(), seed=opts.seed,
                        texel_m=opts.texel_m)
    noise = ColourNoise((opts.height, opts.width), opts.pixel_noise_dn, opts.seed)
    t = np.arange(0.0, opts.seconds, 1.0 / opts.camera_hz)
    p, r_w_b = Flight(scen).body_pose(t)
    r_w_c = r_w_b @ mount_rotation(opts.mount)
    for k in range(len(t)):
        renderer.render(r_w_c[k], p[k])
    out: dict[str, list[float]] = {"render_cpu": [], "all_cpu": [], "all_wall": []}
    for k in range(len(t)):
        w0, c0 = time.perf_counter(), time.thread_time()
        view = renderer.render(r_w_c[k], p[k])
        c1 = time.thread_time()
        rng = np.random.default_rng([opts.seed, 1, k])
        depth_to_png_units(measure_depth(view.depth_m, opts.depth, rng), opts.depth_scale)
        noise.apply(view.bgr, rng)
        c2, w1 = time.thread_time(), time.perf_counter()
        out["render_cpu"].append((c1 - c0) * 1e3)
        out["all_cpu"].append((c2 - c0) * 1e3)
        out["all_wall"].append((w1 - w0) * 1e3)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scenarios", nargs="*", default=list(SCENARIOS), metavar="SCENARIO")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    opts = SimOptions(seconds=args.seconds, width=args.width, height=args.height)
    print(f"{args.width}x{args.height}, ms per frame (median / p95) and frames/s at the median")
    for name in args.scenarios:
        res = bench(name, opts)
        cells = []
        for key, label in (("render_cpu", "render CPU"), ("all_cpu", "+ sensors CPU"),
                           ("all_wall", "+ sensors wall")):
            ms = np.asarray(res[key])
            med = float(np.median(ms))
            cells.append(f"{label} {med:5.1f} / {np.percentile(ms, 95):5.1f} ({1e3 / med:3.0f}/s)")
        print(f"{name:10s} " + "   ".join(cells))
    return 0


if __name__ == "__main__":
    sys.exit(main())
