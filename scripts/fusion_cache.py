"""Tune the fused tracker offline: run each tracker over a sequence once,
keep its per-frame TrackResults, then replay the fusion alone on them
(seconds per try instead of minutes).

    python scripts/fusion_cache.py record SEQ CACHE.pkl [--set section.key=value ...]
    python scripts/fusion_cache.py fuse CACHE.pkl [CACHE2.pkl ...] [--set fusion.key=value ...]
    python scripts/fusion_cache.py why CACHE.pkl [...] [--set ...]   (why the coverage is off)
    python scripts/fusion_cache.py checks CACHE.pkl [...] [--set ...]   (what the outlier check left out)

`record` runs NI-SLAM and FastORB separately on every frame of SEQ, built and
fed as the fused tracker builds and feeds them (`registry.fused_parts`, the
attitude without widening; it runs them independently too, so their results
are the same) from the replay's attitude source, and pickles the results (key-frame clouds dropped),
the attitude and the ground truth. `fuse` runs onboard.fusion.fused on each
cache and prints ATE, per-frame RPE (lags 1/3/10/30 frames), path ratio,
sigma-1 coverage, posed share and resets, with the trackers alone for
reference (each scored the same way). `why` says where the covariance is
off: per axis the fused coverage and rms error against rms sd, and per
tracker each measurement's error against the truth (the filter's clones
shadowed with the ground-truth position of the frame they were made at), split
into the part shared by every frame on one anchor (the key's) and the rest,
each against what the model puts there (the clone's widening, R).
"""

from __future__ import annotations

import argparse
import dataclasses
import pickle
import sys
import time
import tomllib
from pathlib import Path

import numpy as np

from onboard.app.bench import replay_attitude
from onboard.app.config import load_config
from onboard.app.replay import TrackLog, evaluate_track, with_stated_ahrs
from onboard.core.attitude_smoothing import without_widening
from onboard.core.evaluation import ground_truth_at
from onboard.fusion.coverage import sigma1_coverage
from onboard.fusion.filter import AnchoredFilter
from onboard.fusion.fused import FusedTracker
from onboard.fusion.params import FusionParams
from onboard.fusion.registry import fused_parts
from sim_replay.tum import open_sequence

TRACKERS = ("nislam", "fastorb")


def _overrides(pairs: list[str]) -> dict[str, str]:
    return dict(p.split("=", 1) for p in pairs)


def _literal(text: str):
    """A TOML literal (1.0, true, 2) as its value; anything else as the string."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def record(seq_dir: str, out: str, sets: list[str]) -> None:
    cfg = load_config(None, {k: _literal(v) for k, v in _overrides(sets).items()})
    seq = open_sequence(seq_dir, cfg.replay.assoc_max_dt_s, cfg.replay.undistort)
    attitude, _ = replay_attitude(seq, cfg)
    cfg = with_stated_ahrs(cfg, seq_dir)
    frames = list(seq.frames())
    results: dict[str, list] = {}
    part_attitude = without_widening(attitude)  # as FusedTracker.track gives its parts
    for tracker in fused_parts(seq.intrinsics, cfg):  # built as the fused tracker builds them
        t0 = time.perf_counter()
        results[tracker.name] = [
            dataclasses.replace(tracker.track(f, part_attitude), finished_keyframes=())
            for f in frames]
        print(f"{seq_dir}: {tracker.name} {len(frames)} frames in {time.perf_counter() - t0:.0f} s",
              file=sys.stderr)
    with open(out, "wb") as fh:
        pickle.dump({"seq": str(seq_dir), "t_s": [f.t_s for f in frames], "attitude": attitude,
                     "groundtruth": seq.groundtruth, "results": results}, fh)


class _Cached:
    """A tracker that returns recorded results in order."""

    def __init__(self, name: str, results: list) -> None:
        self.name = name
        self._it = iter(results)

    def track(self, frame, attitude):
        return next(self._it)

    def finish(self) -> None:
        return None


@dataclasses.dataclass
class _Frame:
    t_s: float


@dataclasses.dataclass
class _Seq:
    groundtruth: object


def score(results: list, gt) -> dict[str, float | None]:
    log = TrackLog()
    for r in results:
        log.frame_ms.append(0.0)
        if r.trusted:
            log.add_pose(r)
    ev = evaluate_track(log, _Seq(gt), 0.1)  # type: ignore[arg-type]
    m = ev.metrics.as_dict() if ev.metrics is not None else {}
    est = log.trajectory()
    g, valid = ground_truth_at(est.t_s, gt, 0.1)
    var = np.asarray(log.var_p_m2).reshape(-1, 3)[valid]
    return {"ate": m.get("ate_rmse_m"), "posed": len(log.t_s) / len(results),
            "resets": results[-1].reset_counter,
            **{f"rpe{k}": m.get(f"rpe_lag{k}_m") for k in (1, 3, 10, 30)},
            "path": m.get("path_length_ratio"),
            "cov": sigma1_coverage(est.p_xyz_m[valid], var, g.p_xyz_m)}


def fuse(cache: dict, params: FusionParams) -> tuple[list, dict, float]:
    trackers = [_Cached(n, cache["results"][n]) for n in TRACKERS]
    fused = FusedTracker(trackers, params)  # type: ignore[arg-type]
    t0 = time.perf_counter()
    out = [fused.track(_Frame(t), cache["attitude"]) for t in cache["t_s"]]  # type: ignore[arg-type]
    ms = (time.perf_counter() - t0) * 1e3 / len(out)
    return out, fused.stats(), ms


class _TruthFilter(AnchoredFilter):
    """The filter, its clones shadowed with the ground truth: each update's
    measurement error against the true motion since the clone's frame."""

    def __init__(self, base: AnchoredFilter, p_true: np.ndarray) -> None:
        super().__init__((base.n - 6) // 3, 0.0, base.V.shape[0])
        self.q, self.p_true, self.k = base.q, p_true, 0
        self.truth: dict[int, tuple[np.ndarray, np.ndarray, int]] = {}
        self.log: list[tuple[int, np.ndarray, np.ndarray, np.ndarray, int]] = []
        self._ids = iter(range(1 << 30))

    def _mark(self, i: int, p: np.ndarray, W: np.ndarray) -> None:
        self.truth[i] = (p, W, next(self._ids))

    def start(self, t_s, p, var_p, speed_sd):  # type: ignore[no-untyped-def]
        super().start(t_s, p, var_p, speed_sd)
        for i in range((self.n - 6) // 3):
            self._mark(i, self.p_true[self.k], np.zeros((3, 3)))

    def anchor(self, i: int) -> None:
        super().anchor(i)
        self._mark(i, self.p_true[self.k], np.zeros((3, 3)))

    def copy(self, src: int, dst: int) -> None:
        super().copy(src, dst)
        self._mark(dst, *self.truth[src][:2])

    def widen(self, i: int, Q: np.ndarray) -> None:
        super().widen(i, Q)
        p, W, c = self.truth[i]
        self.truth[i] = (p, W + Q, c)

    def update(self, i: int, z: np.ndarray, R: np.ndarray) -> None:
        p, W, c = self.truth[i]
        self.log.append((i, z - (self.p_true[self.k] - p), R.copy(), W.copy(), c))
        super().update(i, z, R)


def why(cache: dict, params: FusionParams, name: str) -> None:
    """Print where the covariance is off (module doc)."""
    t = np.asarray(cache["t_s"])
    g, valid = ground_truth_at(t, cache["groundtruth"], 0.1)
    p_true = np.full((len(t), 3), np.nan)
    p_true[valid] = g.p_xyz_m
    trackers = [_Cached(n, cache["results"][n]) for n in TRACKERS]
    fused = FusedTracker(trackers, params)  # type: ignore[arg-type]
    f = fused.filter = _TruthFilter(fused.filter, p_true)
    out = []
    for k, ts in enumerate(t):
        f.k = k
        out.append(fused.track(_Frame(ts), cache["attitude"]))  # type: ignore[arg-type]
    log = TrackLog()
    for r in out:
        if r.trusted:
            log.add_pose(r)
    est = log.trajectory()
    gg, ok = ground_truth_at(est.t_s, cache["groundtruth"], 0.1)
    e = (est.p_xyz_m[ok] - est.p_xyz_m[ok][0]) - (gg.p_xyz_m - gg.p_xyz_m[0])
    var = np.asarray(log.var_p_m2).reshape(-1, 3)[ok]
    cov = np.mean(np.abs(e) <= np.sqrt(var), axis=0)
    print(f"{name}: fused coverage x/y/z {' '.join(f'{100 * c:.0f}' for c in cov)} %, rms error "
          f"{' '.join(f'{v:.1f}' for v in 1e3 * np.sqrt(np.mean(e**2, 0)))} mm against rms sd "
          f"{' '.join(f'{v:.1f}' for v in 1e3 * np.sqrt(np.mean(var, 0)))} mm")
    owner = {s: link.name for link in fused.links for s in (2 * link.index, 2 * link.index + 1)}
    for link in fused.links:
        rows = [row for row in f.log if owner.get(row[0], fused.links[0].name) == link.name]
        rows = [row for row in rows if np.all(np.isfinite(row[1]))]
        if not rows:
            continue
        groups: dict[int, list] = {}
        for row in rows:
            groups.setdefault(row[4], []).append(row)
        shared = np.array([np.mean([r[1] for r in g_], axis=0) for g_ in groups.values()])
        rest = np.concatenate([np.array([r[1] for r in g_]) - np.mean([r[1] for r in g_], axis=0)
                               for g_ in groups.values()])
        R = np.array([np.diag(r[2]) for r in rows])
        W = np.array([np.diag(g_[0][3]) for g_ in groups.values()])
        inside = np.mean([np.all(np.abs(r[1]) <= np.sqrt(np.diag(r[2] + r[3]))) for r in rows])
        print(f"  {link.name}: {len(rows)} measurements on {len(groups)} anchors; shared "
              f"{1e3 * np.sqrt(np.mean(shared**2)):.1f} mm (model {1e3 * np.sqrt(np.mean(W)):.1f}), rest "
              f"{1e3 * np.sqrt(np.mean(rest**2)):.1f} mm (model {1e3 * np.sqrt(np.mean(R)):.1f}); "
              f"all three axes within 1 sd {100 * inside:.0f} %")


def checks(cache: dict, params: FusionParams, name: str) -> None:
    """Print each frame the outlier check against the other tracker left out
    (onboard.fusion.agreement): d^2 and the bound, and the error of the
    tracker left out and of the one that updated first, against the truth
    (the clones shadowed as in `why`), with the sd each claimed."""
    t = np.asarray(cache["t_s"])
    g, valid = ground_truth_at(t, cache["groundtruth"], 0.1)
    p_true = np.full((len(t), 3), np.nan)
    p_true[valid] = g.p_xyz_m
    fused = FusedTracker([_Cached(n, cache["results"][n]) for n in TRACKERS], params)  # type: ignore[arg-type]
    f = fused.filter = _TruthFilter(fused.filter, p_true)
    owner = {s: link.name for link in fused.links for s in (2 * link.index, 2 * link.index + 1)}
    nis, seen = f.nis, []

    def nis_logged(i: int, z: np.ndarray, R: np.ndarray) -> float:
        p, _, _ = f.truth[i]
        seen.append((i, z - (f.p_true[f.k] - p), R))
        return nis(i, z, R)

    f.nis = nis_logged  # type: ignore[method-assign]
    check = fused._outliers.check

    def check_logged(d2: float) -> bool:
        bound = fused._outliers.bound()
        out = check(d2)
        if out:
            i, e, R = seen[-1]
            j, e1, R1 = f.log[-1][:3]

            def mm(v: np.ndarray) -> float:
                return 1e3 * float(np.linalg.norm(v))
            print(f"  frame {f.k:4d}  d2 {d2:6.1f} > {bound:5.1f}  left out {owner.get(i, 'nislam'):7s} "
                  f"{mm(e):5.1f} mm off (sd {mm(np.sqrt(np.diag(R))):4.1f})  first "
                  f"{owner.get(j, 'nislam'):7s} {mm(e1):5.1f} mm (sd {mm(np.sqrt(np.diag(R1))):4.1f})")
        return out

    fused._outliers.check = check_logged  # type: ignore[method-assign]
    print(f"{name}: frames the outlier check left out (errors against the truth; nan: no ground truth)")
    for k, ts in enumerate(t):
        f.k = k
        fused.track(_Frame(ts), cache["attitude"])  # type: ignore[arg-type]


def _line(label: str, s: dict) -> str:
    def mm(v: float | None) -> str:
        return "   -  " if v is None else f"{v * 1e3:6.1f}"
    cov = "  -" if s["cov"] is None else f"{100 * s['cov']:3.0f}"
    path = "  -  " if s["path"] is None else f"{s['path']:.3f}"
    return (f"{label:28s} ATE {mm(s['ate'])} mm  posed {100 * s['posed']:5.1f} %  resets "
            f"{s['resets']:3d}  RPE1/3/10/30 {mm(s['rpe1'])}{mm(s['rpe3'])}{mm(s['rpe10'])}"
            f"{mm(s['rpe30'])} mm  path {path}  cov {cov} %")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record")
    r.add_argument("seq")
    r.add_argument("out")
    r.add_argument("--set", action="append", default=[])
    f = sub.add_parser("fuse")
    f.add_argument("caches", nargs="+")
    f.add_argument("--set", action="append", default=[])
    f.add_argument("--alone", action="store_true", help="also score each tracker alone")
    for cmd in ("why", "checks"):
        w = sub.add_parser(cmd)
        w.add_argument("caches", nargs="+")
        w.add_argument("--set", action="append", default=[])
    a = ap.parse_args()
    if a.cmd == "record":
        record(a.seq, a.out, a.set)
        return
    fusion_sets = {k.removeprefix("fusion."): v for k, v in _overrides(a.set).items()}
    base = FusionParams()
    params = dataclasses.replace(
        base, **{k: type(getattr(base, k))(_literal(v)) for k, v in fusion_sets.items()})
    for path in a.caches:
        with open(path, "rb") as fh:
            cache = pickle.load(fh)
        name = Path(path).stem
        if a.cmd in ("why", "checks"):
            (why if a.cmd == "why" else checks)(cache, params, name)
            continue
        if a.alone:
            for n in TRACKERS:
                print(_line(f"{name} {n}", score(cache["results"][n], cache["groundtruth"])))
        out, stats, ms = fuse(cache, params)
        s = score(out, cache["groundtruth"])
        left = {n: sum(t["left_out"].values()) for n, t in stats["trackers"].items()}
        print(_line(f"{name} fused", s) + f"  {ms:.2f} ms/frame  left out {left}  scale {stats['noise_scale']}")


if __name__ == "__main__":
    main()
