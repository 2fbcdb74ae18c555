"""FastORB tracker on synthetic RGB-D flights with exact ground truth, and its
parts: the uniform-acceleration model, the grid motion statistic, the
epipolar filter, key-frame clouds, loss and re-localisation.

The scene is ray-cast here (sim_replay has scene geometry but no renderer
yet): a room of textured planes with exact depth. The camera's true pose is
known, so frame-to-frame relative poses can be checked to sub-millimetre.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import pytest
from scipy.ndimage import gaussian_filter
from scipy.spatial.transform import Rotation

from onboard.core.camera import CameraIntrinsics
from onboard.core.messages import RgbdFrame, TrackState
from onboard.core.se3 import inverse, make_pose, se3_exp, se3_log, se3_power
from onboard.fastorb.matching import epipolar_inliers, gms_inliers, hamming, match_by_projection
from onboard.fastorb.motion import FrameClock, predict_uam
from onboard.fastorb.params import FastOrbParams
from onboard.fastorb.tracker import FastOrbTracker

INTR = CameraIntrinsics(fx=517.3, fy=516.5, cx=318.6, cy=255.3, width=640, height=480)
K = np.array([[INTR.fx, 0, INTR.cx], [0, INTR.fy, INTR.cy], [0, 0, 1.0]])
DT = 1.0 / 30.0
TEXEL_M = 0.004


# ------------------------------------------------------------------ scene
def _texture(seed: int, n: int = 1024) -> np.ndarray:
    """Periodic blocky texture (corners for ORB) softened to ~1 texel."""
    rng = np.random.default_rng(seed)
    tex = np.zeros((n, n), np.float32)
    for block in (8, 16, 32):
        coarse = rng.uniform(-1, 1, (n // block, n // block)).astype(np.float32)
        tex += np.kron(coarse, np.ones((block, block), np.float32)) / block**0.5
    tex = gaussian_filter(tex, 1.2, mode="wrap")
    return np.clip(128 + 50 * tex / tex.std(), 0, 255).astype(np.float32)


@dataclass(frozen=True)
class Plane:
    origin: np.ndarray
    u: np.ndarray  # unit, along texture columns
    v: np.ndarray  # unit, along texture rows
    size_m: tuple[float, float] | None  # None: unbounded
    texture: np.ndarray


class Room:
    """Back wall (z = 3 m), a box face (z = 1.8 m), floor (y = 1 m) and a
    side wall (x = -1.6 m), all in the world frame = the first camera's axes
    (x right, y down, z forward)."""

    def __init__(self, seed: int = 0):
        ex, ey, ez = np.eye(3)
        self.planes = [
            Plane(np.array([-4.0, -3.0, 3.0]), ex, ey, None, _texture(seed)),
            Plane(np.array([-0.6, -0.4, 1.8]), ex, ey, (0.9, 0.8), _texture(seed + 1)),
            Plane(np.array([-4.0, 1.0, 0.0]), ex, ez, (8.0, 3.0), _texture(seed + 2)),
            Plane(np.array([-1.6, -3.0, 0.0]), ez, ey, (3.0, 6.0), _texture(seed + 3)),
        ]
        u = (np.arange(INTR.width) - INTR.cx) / INTR.fx
        v = (np.arange(INTR.height) - INTR.cy) / INTR.fy
        self._rays_C = np.stack(np.broadcast_arrays(u[None, :], v[:, None], 1.0), axis=-1)

    def render(self, R_W_C: np.ndarray, c_W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """BGR uint8 and depth (float32 m, 0 = nothing) seen from pose (R_W_C, c_W)."""
        rays = self._rays_C @ R_W_C.T  # camera z component 1: ray length = depth
        depth = np.full(rays.shape[:2], np.inf)
        gray = np.zeros(rays.shape[:2], np.float32)
        for pl in self.planes:
            n = np.cross(pl.u, pl.v)
            with np.errstate(divide="ignore", invalid="ignore"):
                s = ((pl.origin - c_W) @ n) / (rays @ n)
            a = (c_W - pl.origin) @ pl.u + s * (rays @ pl.u)
            b = (c_W - pl.origin) @ pl.v + s * (rays @ pl.v)
            hit = np.isfinite(s) & (s > 0.05) & (s < depth)
            if pl.size_m is not None:
                hit &= (a >= 0) & (a <= pl.size_m[0]) & (b >= 0) & (b <= pl.size_m[1])
            n_tex = pl.texture.shape[0]
            mx = np.where(hit, a / TEXEL_M, 0.0).astype(np.float32) % n_tex
            my = np.where(hit, b / TEXEL_M, 0.0).astype(np.float32) % n_tex
            g = cv2.remap(pl.texture, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
            depth = np.where(hit, s, depth)
            gray = np.where(hit, g, gray)
        depth = np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)
        g8 = np.clip(np.round(gray), 0, 255).astype(np.uint8)
        return cv2.cvtColor(g8, cv2.COLOR_GRAY2BGR), depth


class NoAttitude:
    def rotation_at(self, t_s: float) -> None:
        return None


class FixedAttitude:
    def __init__(self, R: np.ndarray):
        self.R = R

    def rotation_at(self, t_s: float) -> np.ndarray:
        return self.R.copy()


def flight(n: int, speed: float = 1.0) -> list[tuple[np.ndarray, np.ndarray]]:
    """Smooth hand-held-like motion: (R_W_C, c_W) per frame, starting at the
    origin looking down +z. `speed` scales the angular and linear rates."""
    out = []
    for k in range(n):
        t = k * DT * speed
        c = np.array([0.3 * np.sin(0.8 * t), 0.1 * np.sin(1.3 * t), 0.2 * np.sin(0.5 * t)])
        euler = [8 * np.sin(1.1 * t), 12 * np.sin(0.9 * t), 6 * np.sin(0.7 * t)]
        out.append((Rotation.from_euler("xyz", euler, degrees=True).as_matrix(), c))
    return out


def pose_matrix(R_W_C: np.ndarray, c_W: np.ndarray) -> np.ndarray:
    """T_W_C (camera -> world)."""
    return make_pose(R_W_C, c_W)


@pytest.fixture(scope="module")
def room() -> Room:
    return Room(seed=3)


@pytest.fixture(scope="module")
def flight_frames(room: Room) -> tuple[list, list[RgbdFrame]]:
    poses = flight(36)
    frames = []
    for k, (R, c) in enumerate(poses):
        bgr, depth = room.render(R, c)
        frames.append(RgbdFrame(k * DT, bgr, depth))
    return poses, frames


def _relative_errors(results, poses) -> list[tuple[float, float]]:
    """(mm, deg) of the estimated frame-to-frame motion against the truth."""
    errs = []
    for k in range(1, len(results)):
        a, b = results[k - 1], results[k]
        est = inverse(pose_matrix(a.R_W_C, a.p_W_m)) @ pose_matrix(b.R_W_C, b.p_W_m)
        true = inverse(pose_matrix(*poses[k - 1])) @ pose_matrix(*poses[k])
        d = inverse(true) @ est
        errs.append((1e3 * float(np.linalg.norm(d[:3, 3])),
                     float(np.degrees(np.linalg.norm(se3_log(d)[:3])))))
    return errs


# ------------------------------------------------------------------ tracking
def test_frame_to_frame_pose_within_2mm_and_0_1deg(flight_frames) -> None:
    """Every frame of a textured synthetic flight is tracked, each relative
    pose within 2 mm / 0.1 deg of the truth (measured: ~0.2-0.6 mm, ~0.01 deg),
    and the first camera is the world origin."""
    poses, frames = flight_frames
    tracker = FastOrbTracker(INTR)
    results = [tracker.track(f, NoAttitude()) for f in frames]
    assert all(r.trusted and r.state is TrackState.TRACKING for r in results)
    np.testing.assert_allclose(results[0].p_W_m, np.zeros(3), atol=1e-12)
    np.testing.assert_allclose(results[0].R_W_C, np.eye(3), atol=1e-12)
    errs = np.array(_relative_errors(results, poses))
    print("relative pose error mm / deg: median", np.median(errs, axis=0), "max", errs.max(axis=0))
    assert errs[:, 0].max() < 2.0
    assert errs[:, 1].max() < 0.1
    # The world is the first camera's: absolute positions match too.
    last = np.array([r.p_W_m for r in results]) - np.array([c for _, c in poses])
    assert np.abs(last).max() < 0.005
    assert results[0].new_keyframe and results[0].reset_counter == 0
    assert all(0 < r.quality <= 100 for r in results)
    assert all(np.all(np.isfinite(r.pose_var)) and np.all(r.pose_var >= 0) for r in results)


def test_world_orientation_from_attitude_at_start(flight_frames) -> None:
    """With an attitude at the first frame the world is the attitude world:
    the first R_W_C is that attitude, later poses are rotated with it."""
    poses, frames = flight_frames
    R0 = Rotation.from_euler("zyx", [30.0, -10.0, 5.0], degrees=True).as_matrix()
    tracker = FastOrbTracker(INTR)
    results = [tracker.track(f, FixedAttitude(R0)) for f in frames[:6]]
    np.testing.assert_allclose(results[0].R_W_C, R0, atol=1e-12)
    for r, (R, c) in zip(results, poses):
        np.testing.assert_allclose(r.R_W_C, R0 @ R, atol=2e-3)
        np.testing.assert_allclose(r.p_W_m, R0 @ c, atol=3e-3)


def test_keyframe_clouds_lie_on_the_scene(flight_frames, room: Room) -> None:
    """Key-frame clouds come out in the NI-SLAM KeyframeCloud form and their
    points lie on the room's planes (within the cell quantisation)."""
    _poses, frames = flight_frames
    tracker = FastOrbTracker(INTR, FastOrbParams(keyframe_max_frames=5))
    clouds = []
    for f in frames[:12]:
        clouds.extend(tracker.track(f, NoAttitude()).finished_keyframes)
    last = tracker.finish()
    assert last is not None
    clouds.append(last)
    assert len(clouds) >= 2
    assert len({c.keyframe_id for c in clouds}) == len(clouds)
    for cloud in clouds:
        xyz, rgb = cloud.points()
        assert len(xyz) > 1000 and rgb.dtype == np.uint8 and rgb.shape == xyz.shape
        # distance to the nearest plane: cells are res_m wide, depth exact
        dist = np.full(len(xyz), np.inf)
        for pl in room.planes:
            n = np.cross(pl.u, pl.v)
            dist = np.minimum(dist, np.abs((xyz - pl.origin) @ n))
        assert np.median(dist) < 0.01
        assert np.percentile(dist, 90) < 3 * cloud.res_m


def test_lost_then_relocalised_bumps_reset_counter(flight_frames) -> None:
    """Blank frames (nothing to track): lost, no pose. Back at a view the key
    frames know after longer than tracking may coast: re-localised against
    them by descriptors, with reset_counter + 1, at the right pose."""
    poses, frames = flight_frames
    tracker = FastOrbTracker(INTR)
    for f in frames[:10]:
        assert tracker.track(f, NoAttitude()).trusted
    blank = RgbdFrame(frames[10].t_s, np.zeros_like(frames[10].bgr), frames[10].depth_m)
    lost = tracker.track(blank, NoAttitude())
    assert not lost.trusted and lost.state is TrackState.LOST
    assert lost.p_W_m is None and lost.R_W_C is None and lost.quality == 0
    assert lost.lost_reason and lost.reset_counter == 0
    for k in range(11, 11 + tracker.p.max_coast_frames):
        blank2 = RgbdFrame(frames[k].t_s, np.zeros_like(frames[k].bgr), frames[k].depth_m)
        still = tracker.track(blank2, NoAttitude())
        assert not still.trusted and still.state is TrackState.LOST
    back = tracker.track(frames[4], NoAttitude())  # a view seen before
    assert back.trusted and back.state is TrackState.TRACKING
    assert back.reset_counter == 1
    np.testing.assert_allclose(back.p_W_m, poses[4][1], atol=0.01)
    after = tracker.track(frames[5], NoAttitude())
    assert after.trusted and after.reset_counter == 1


def test_one_blank_frame_is_bridged_without_a_reset(flight_frames) -> None:
    """One unusable frame (tum_fr1_rpy: motion blur) loses the track; the next
    re-localises where the motion model expects it: the same map, no jump, so
    no reset for the autopilot, and the pose is right."""
    poses, frames = flight_frames
    tracker = FastOrbTracker(INTR)
    for f in frames[:10]:
        assert tracker.track(f, NoAttitude()).trusted
    blank = RgbdFrame(frames[10].t_s, np.zeros_like(frames[10].bgr), frames[10].depth_m)
    assert tracker.track(blank, NoAttitude()).state is TrackState.LOST
    back = tracker.track(frames[11], NoAttitude())
    assert back.trusted and back.reset_counter == 0
    np.testing.assert_allclose(back.p_W_m, poses[11][1], atol=0.02)  # re-localised: ~1 cm
    assert tracker.track(frames[12], NoAttitude()).reset_counter == 0


def test_same_input_same_output(flight_frames) -> None:
    """A pure core: two trackers fed the same frames agree exactly."""
    _poses, frames = flight_frames
    a, b = FastOrbTracker(INTR), FastOrbTracker(INTR)
    for f in frames[:8]:
        ra, rb = a.track(f, NoAttitude()), b.track(f, NoAttitude())
        np.testing.assert_array_equal(ra.p_W_m, rb.p_W_m)
        np.testing.assert_array_equal(ra.R_W_C, rb.R_W_C)


def test_too_little_texture_stays_initialising() -> None:
    blank = RgbdFrame(0.0, np.zeros((480, 640, 3), np.uint8), np.ones((480, 640), np.float32))
    res = FastOrbTracker(INTR).track(blank, NoAttitude())
    assert not res.trusted and res.state is TrackState.INITIALIZING and res.p_W_m is None


# ------------------------------------------------------------------ motion model
def _random_twist(rng: np.random.Generator, rot: float, trans: float) -> np.ndarray:
    return np.concatenate([rng.normal(0, rot, 3), rng.normal(0, trans, 3)])


def test_uam_exact_for_constant_acceleration_equal_steps() -> None:
    """Eq. 14: with the velocity increment A constant (D_k = A^k D_0,
    T_{k+1} = D_k T_k) the prediction is exact."""
    rng = np.random.default_rng(1)
    A = se3_exp(_random_twist(rng, 0.01, 0.005))
    D = se3_exp(_random_twist(rng, 0.05, 0.02))
    T = [se3_exp(_random_twist(rng, 0.5, 1.0))]
    for _ in range(5):
        T.append(D @ T[-1])
        D = A @ D
    times = [k * DT for k in range(len(T))]
    for k in range(3, len(T)):
        pred = predict_uam(times[k - 3:k], T[k - 3:k], times[k])
        np.testing.assert_allclose(pred, T[k], atol=1e-9)
    # The paper's closed form, Eq. 14 then Eq. 15:
    T1, T2, T3 = T[2], T[1], T[0]
    eq14 = T1 @ inverse(T2) @ T3 @ inverse(T2) @ T1 @ inverse(T2)
    np.testing.assert_allclose(eq14 @ T1, T[3], atol=1e-9)


def test_uam_exact_for_constant_acceleration_with_dropped_frames() -> None:
    """Uneven intervals (a dropped frame): exact for a translation with
    constant acceleration and for a rotation about a fixed axis with constant
    angular acceleration."""
    times = np.array([0.0, 1.0, 3.0, 4.0]) * DT  # frame 2 dropped
    a, v, p0 = np.array([2.0, -1.0, 0.5]), np.array([0.1, 0.3, -0.2]), np.array([1.0, 2.0, 3.0])
    trans = [make_pose(np.eye(3), -(p0 + v * t + 0.5 * a * t * t)) for t in times]
    np.testing.assert_allclose(predict_uam(times[:3], trans[:3], times[3]), trans[3], atol=1e-12)
    axis = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    angle = [0.2 + 1.5 * t + 0.5 * 40.0 * t * t for t in times]
    rots = [make_pose(Rotation.from_rotvec(axis * g).as_matrix(), np.zeros(3)) for g in angle]
    np.testing.assert_allclose(predict_uam(times[:3], rots[:3], times[3]), rots[3], atol=1e-12)


def test_uam_with_fewer_poses_and_constant_velocity_gain() -> None:
    rng = np.random.default_rng(2)
    T0 = se3_exp(_random_twist(rng, 0.3, 0.5))
    D = se3_exp(_random_twist(rng, 0.05, 0.02))
    np.testing.assert_array_equal(predict_uam([0.0], [T0], DT), T0)
    np.testing.assert_allclose(predict_uam([0.0, DT], [T0, D @ T0], 2 * DT), D @ D @ T0,
                               atol=1e-12)
    T = [T0, D @ T0, D @ D @ T0]
    A = se3_exp(_random_twist(rng, 0.01, 0.01))
    T[2] = A @ D @ T[1]  # accelerating: gain 0 ignores it
    cv = predict_uam([0.0, DT, 2 * DT], T, 3 * DT, accel_gain=0.0)
    np.testing.assert_allclose(cv, T[2] @ inverse(T[1]) @ T[2], atol=1e-12)


def test_se3_exp_log_round_trip() -> None:
    rng = np.random.default_rng(3)
    for _ in range(20):
        xi = _random_twist(rng, 0.8, 2.0)
        np.testing.assert_allclose(se3_log(se3_exp(xi)), xi, atol=1e-9)
        T = se3_exp(xi)
        np.testing.assert_allclose(se3_power(T, 0.5) @ se3_power(T, 0.5), T, atol=1e-9)


def test_frame_clock_counts_whole_periods() -> None:
    """Jittery stamps (28-40 ms around 33 ms) become whole periods; a dropped
    frame counts two."""
    rng = np.random.default_rng(4)
    clock = FrameClock()
    stamps, t = [], 100.0
    for k in range(40):
        t += (2 if k == 25 else 1) * 0.0333 + rng.uniform(-0.006, 0.006)
        stamps.append(t)
    times, periods = [], []
    for s in stamps:
        times.append(clock(s))
        periods.append(clock.period)  # the period the step was counted in
    steps = np.diff(times) / np.array(periods[1:])
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-9)
    assert np.round(steps).tolist() == [1.0] * 24 + [2.0] + [1.0] * 14
    assert abs(clock.period - 0.0333) < 0.003


# ------------------------------------------------------------------ outlier rejection
def _smooth_matches(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Points under a small rotation + zoom + shift: a smooth flow field."""
    p0 = rng.uniform([0, 0], [640, 480], (n, 2))
    c = np.array([320.0, 240.0])
    a = np.radians(2.0)
    R = 1.02 * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    p1 = (p0 - c) @ R.T + c + np.array([12.0, -7.0]) + rng.normal(0, 0.3, (n, 2))
    return p0, p1


def test_gms_rejects_injected_outliers() -> None:
    rng = np.random.default_rng(5)
    p0, p1 = _smooth_matches(rng, 800)
    bad = rng.choice(800, 120, replace=False)
    p1[bad] = rng.uniform([0, 0], [640, 480], (120, 2))  # matches gone wrong
    keep = gms_inliers(p0, p1, (640, 480), (16, 12), 6.0)
    good = np.setdiff1d(np.arange(800), bad)
    print("GMS kept", keep[good].mean(), "of inliers,", keep[bad].mean(), "of outliers")
    assert keep[good].mean() > 0.95
    assert keep[bad].mean() < 0.05
    assert gms_inliers(p0[:0], p1[:0], (640, 480), (16, 12), 6.0).shape == (0,)


def _gms_numpy(p0, p1, size_wh, grid_cr, alpha) -> np.ndarray:
    """The grid motion statistic as first written in numpy (bincounts and
    nine flat-offset gathers per placement): the compiled one's reference."""
    n = len(p0)
    keep = np.zeros(n, bool)
    (w, h), (cols, rows) = size_wh, grid_cr
    cw, ch = w / cols, h / rows
    bx = np.clip((p1[:, 0] / cw).astype(np.int64), 0, cols - 1) + 1
    by = np.clip((p1[:, 1] / ch).astype(np.int64), 0, rows - 1) + 1
    right = (rows + 2, cols + 2)
    n_right = right[0] * right[1]
    right_cell = by * right[1] + bx
    for sx, sy in ((0.0, 0.0), (0.5, 0.0), (0.0, 0.5), (0.5, 0.5)):
        lc, lr = cols + (sx > 0), rows + (sy > 0)
        ax = np.clip(((p0[:, 0] + sx * cw) / cw).astype(np.int64), 0, lc - 1) + 1
        ay = np.clip(((p0[:, 1] + sy * ch) / ch).astype(np.int64), 0, lr - 1) + 1
        width = lc + 2
        cell = ay * width + ax
        pair = cell * n_right + right_cell
        pairs = np.bincount(pair, minlength=(lr + 2) * width * n_right)
        per_cell = np.bincount(cell, minlength=(lr + 2) * width)
        has_cell = np.zeros((lr + 2, width), np.int64)
        has_cell[1:-1, 1:-1] = 1
        has_cell = has_cell.ravel()
        support, total, cells = (np.zeros(n, np.int64) for _ in range(3))
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                d_left = dy * width + dx
                support += pairs[pair + d_left * n_right + dy * right[1] + dx]
                total += per_cell[cell + d_left]
                cells += has_cell[cell + d_left]
        keep |= support > alpha * np.sqrt(total / np.maximum(cells, 1))
    return keep


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_gms_compiled_equals_numpy_reference(dtype) -> None:
    """Same keep mask as the numpy form, points on cell borders and outside
    the image included, in the tracker's float32 pixels too."""
    rng = np.random.default_rng(11)
    p0, p1 = _smooth_matches(rng, 900)
    p1[rng.choice(900, 200, replace=False)] = rng.uniform([-20, -20], [660, 500], (200, 2))
    p0[:40] = np.round(p0[:40] / 40.0) * 40.0  # exactly on cell borders (40 px cells)
    p0, p1 = p0.astype(dtype), p1.astype(dtype)
    for alpha in (2.0, 6.0):
        np.testing.assert_array_equal(gms_inliers(p0, p1, (640, 480), (16, 12), alpha),
                                      _gms_numpy(p0, p1, (640, 480), (16, 12), alpha))


def test_epipolar_ransac_rejects_off_line_matches(flight_frames) -> None:
    """Real two-view geometry from the synthetic flight: matches moved off
    their epipolar line by 5 px are rejected, the true ones kept."""
    poses, _frames = flight_frames
    rng = np.random.default_rng(6)
    X = np.column_stack([rng.uniform(-1.5, 1.5, 400), rng.uniform(-1, 1, 400),
                         rng.uniform(1.5, 4.0, 400)])

    def proj(R_W_C: np.ndarray, c: np.ndarray) -> np.ndarray:
        p = (X - c) @ R_W_C
        return (p[:, :2] / p[:, 2:]) * [INTR.fx, INTR.fy] + [INTR.cx, INTR.cy]

    p0, p1 = proj(*poses[0]), proj(*poses[20])
    bad = rng.choice(400, 60, replace=False)
    p1[bad] += rng.choice([-1, 1], (60, 1)) * np.array([[5.0, -5.0]])
    keep = epipolar_inliers(p0, p1, 1.0, 0.99)
    assert keep[np.setdiff1d(np.arange(400), bad)].mean() > 0.95
    assert keep[bad].mean() < 0.2


def test_match_by_projection_gates_by_radius_and_distance() -> None:
    rng = np.random.default_rng(7)
    desc = rng.integers(0, 256, (50, 32), dtype=np.uint8)
    uv = rng.uniform(0, 600, (50, 2))
    map_desc = desc.copy()
    map_desc[:, 0] ^= 0b111  # 3 bits differ: still a match
    map_uv = uv + 3.0
    map_uv[10] += 100.0  # projected far away: no match for 10
    kp_i, map_i = match_by_projection(desc, uv, map_desc, map_uv, 15.0, 50)
    assert set(zip(kp_i.tolist(), map_i.tolist())) == {(i, i) for i in range(50) if i != 10}
    assert np.all(hamming(desc[kp_i], map_desc[map_i]) == 3)


def test_match_by_projection_equals_brute_force() -> None:
    """Every keypoint / projection pair within the radius is compared (the
    compiled search bins keypoints by the radius): the same one-to-one
    matches as comparing all pairs, nearest descriptor first."""
    rng = np.random.default_rng(12)
    desc = rng.integers(0, 256, (600, 32), dtype=np.uint8)
    uv = rng.uniform(-5, 645, (600, 2))
    src = rng.permutation(600)[:400]
    map_desc = desc[src].copy()
    map_desc[:, :4] ^= rng.integers(0, 256, (400, 4), dtype=np.uint8)  # about 16 bits apart
    map_uv = uv[src] + rng.normal(0, 6.0, (400, 2))  # some beyond the radius
    kp_i, map_i = match_by_projection(desc, uv, map_desc, map_uv, 15.0, 40)
    d = np.array([[hamming(desc[i:i + 1], map_desc[j:j + 1])[0] for j in range(400)]
                  for i in range(600)])
    near = np.linalg.norm(uv[:, None] - map_uv[None], axis=2) <= 15.0
    q, t = np.nonzero(near & (d <= 40))
    order = np.lexsort((q, t, d[q, t]))  # by distance, then map point, then keypoint
    used_q, used_t, want = set(), set(), []
    for i, j in zip(q[order], t[order]):
        if i not in used_q:
            used_q.add(i)
            want.append((i, j))
    ref = [(i, j) for i, j in want if not (j in used_t or used_t.add(j))]
    assert 200 < len(ref) < 400
    assert list(zip(kp_i.tolist(), map_i.tolist())) == ref


# ------------------------------------------------------------------ config and factory
def test_config_section_reaches_the_tracker() -> None:
    """[fastorb] is read from FastOrbParams; its values reach the tracker and
    the range rules name the key."""
    from onboard import NislamError
    from onboard.app.config import load_config
    from onboard.fusion.registry import make_tracker

    cfg = load_config(None, {"tracker.name": "fastorb", "fastorb.orb_features": 500,
                             "fastorb.use_motion_model": False})
    tracker = make_tracker(cfg.tracker.name, INTR, cfg)
    assert isinstance(tracker, FastOrbTracker)
    assert tracker.p.orb_features == 500 and tracker.p.use_motion_model is False
    with pytest.raises(NislamError, match="'fastorb.min_inliers' must be >= 6"):
        load_config(None, {"fastorb.min_inliers": 3})
    with pytest.raises(NislamError, match="'fastorb.min_depth_m'"):
        load_config(None, {"fastorb.min_depth_m": 7.0})


def test_motion_model_seeding_keeps_more_matches_on_fast_motion(room: Room) -> None:
    """Table I in miniature: under fast motion (4 x the test flight's rates)
    LK seeded by the UAM prediction (Eq. 16) keeps far more verified, correct
    matches than plain KLT from the old positions (measured: 0.96 vs 0.20)."""
    from onboard.fastorb.local_map import sample_depth
    from onboard.fastorb.matching import LkSettings, track_lk
    from onboard.fastorb.motion import back_project, project

    poses = flight(4, speed=4.0)
    T_cw = [inverse(pose_matrix(R, c)) for R, c in poses]
    grays = [cv2.cvtColor(room.render(R, c)[0], cv2.COLOR_BGR2GRAY) for R, c in poses]
    uv = np.array([k.pt for k in cv2.ORB_create(1000).detect(grays[2], None)], np.float64)
    z = sample_depth(room.render(*poses[2])[1], uv, 0.2, 6.0, 0.05)
    uv, z = uv[z > 0], z[z > 0]
    prior = predict_uam([0.0, DT, 2 * DT], T_cw[:3], 3 * DT)
    seed, _ = project(K, prior, back_project(K, T_cw[2], uv, z))
    ratios = {}
    for name, start in (("klt", None), ("uam", seed)):
        moved, ok = track_lk(grays[2], grays[3], uv, start, LkSettings())
        idx = np.flatnonzero(ok)
        idx = idx[gms_inliers(uv[idx], moved[idx], (640, 480), (16, 12), 6.0)]
        keep = epipolar_inliers(uv[idx], moved[idx], 2.0, 0.99)
        true_uv, _ = project(K, T_cw[3], back_project(K, T_cw[2], uv[idx][keep], z[idx][keep]))
        right = np.linalg.norm(moved[idx][keep] - true_uv, axis=1) < 1.0
        ratios[name] = right.sum() / len(uv)
    print("verified and right / keypoints:", ratios)
    assert ratios["uam"] > 0.8
    assert ratios["uam"] > ratios["klt"] + 0.2


# ------------------------------------------------------------------ pose refinement
def test_rgbd_residual_jacobian_matches_finite_differences() -> None:
    """The disparity row (bf / z, ORB-SLAM2's RGB-D term) and the pixel rows
    of the refinement's Jacobian agree with central differences of the
    residuals under a left perturbation exp(xi^) T_cw."""
    from onboard.fastorb.pose import _residuals

    rng = np.random.default_rng(8)
    obj = np.column_stack([rng.uniform(-1, 1, 20), rng.uniform(-1, 1, 20), rng.uniform(1, 3, 20)])
    img = rng.uniform(0, 600, (20, 2))
    disp = np.where(np.arange(20) % 3 == 0, 0.0, rng.uniform(10, 40, 20))  # some without depth
    T = se3_exp(_random_twist(rng, 0.1, 0.1))
    res, J = _residuals(T, obj, img, disp, K, 40.0)
    assert np.all(res[disp == 0, 2] == 0) and np.all(J[disp == 0, 2] == 0)
    h = 1e-6
    for k in range(6):
        d = np.zeros(6)
        d[k] = h
        num = (_residuals(se3_exp(d) @ T, obj, img, disp, K, 40.0)[0]
               - _residuals(se3_exp(-d) @ T, obj, img, disp, K, 40.0)[0]) / (2 * h)
        np.testing.assert_allclose(J[:, :, k], num, rtol=1e-5, atol=1e-4)


def test_compiled_normal_equations_match_the_residuals() -> None:
    """The refinement's one-pass Gauss-Newton system (and the gates' residual
    norms) equal those built from `_residuals` with Huber weights, points
    without depth and unselected points included."""
    from onboard.fastorb.kernels import pose_normal_equations, pose_residual_norms
    from onboard.fastorb.pose import _residuals

    rng = np.random.default_rng(13)
    obj = np.column_stack([rng.uniform(-1, 1, 60), rng.uniform(-1, 1, 60), rng.uniform(1, 3, 60)])
    img = rng.uniform(0, 600, (60, 2))
    disp = np.where(np.arange(60) % 4 == 0, 0.0, rng.uniform(10, 40, 60))
    sel = rng.uniform(size=60) < 0.7
    T = se3_exp(_random_twist(rng, 0.1, 0.1))
    for bf, huber in ((40.0, 1.0), (0.0, 1.0), (40.0, 0.0)):
        res, J = _residuals(T, obj, img, disp, K, bf)
        norm = np.linalg.norm(res, axis=1)
        w = np.ones(60) if huber <= 0 else np.where(norm <= huber, 1.0, huber / norm)
        w, r, Js = w[sel], res[sel], J[sel]
        H, g, sse_w, sse_px, n_obs, n = pose_normal_equations(
            T[:3, :3].copy(), T[:3, 3].copy(), obj, img, disp, sel, K[0, 0], K[1, 1], K[0, 2],
            K[1, 2], bf, huber)
        np.testing.assert_allclose(H, np.einsum("n,nki,nkj->ij", w, Js, Js), rtol=1e-12)
        np.testing.assert_allclose(g, np.einsum("n,nki,nk->i", w, Js, r), rtol=1e-12)
        np.testing.assert_allclose(sse_w, np.sum(w * np.sum(r**2, axis=1)), rtol=1e-12)
        np.testing.assert_allclose(sse_px, np.sum(r[:, :2] ** 2), rtol=1e-12)
        assert n == sel.sum() and n_obs == 2 * n + (bf > 0) * np.count_nonzero(disp[sel] > 0)
        np.testing.assert_allclose(pose_residual_norms(T[:3, :3].copy(), T[:3, 3].copy(), obj, img,
                                                       disp, K[0, 0], K[1, 1], K[0, 2], K[1, 2],
                                                       bf), norm, rtol=1e-12)


def test_sample_depth_equals_numpy_reference() -> None:
    """The compiled depth look-up gives the numpy form's values bit for bit:
    bilinear inside a surface, 0 on depth edges, holes and out of range."""
    from onboard.fastorb.local_map import sample_depth

    rng = np.random.default_rng(14)
    depth = rng.uniform(0.5, 4.0, (48, 64)).astype(np.float32)
    depth[10:20, 10:30] = 2.0  # flat patches pass the edge test
    depth[30:40, 30:50] = np.linspace(1.0, 1.2, 20, dtype=np.float32)
    depth[5:8, 40:44] = 0.0
    uv = np.concatenate([rng.uniform(-3, 67, (300, 2)), rng.uniform([11, 11], [28, 18], (50, 2)),
                         rng.uniform([31, 31], [48, 38], (50, 2))])
    for pts in (uv, uv.astype(np.float32)):
        h, w = depth.shape
        x, y = np.clip(pts[:, 0], 1.0, w - 3.0), np.clip(pts[:, 1], 1.0, h - 3.0)
        u0, v0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
        fx, fy = x - u0, y - v0
        dv, du = np.repeat(np.arange(-1, 3), 4), np.tile(np.arange(-1, 3), 4)
        win = depth[v0[:, None] + dv, u0[:, None] + du].astype(np.float64)
        z = ((win[:, 5] * (1 - fx) + win[:, 6] * fx) * (1 - fy)
             + (win[:, 9] * (1 - fx) + win[:, 10] * fx) * fy)
        lo, hi = win.min(axis=1), win.max(axis=1)
        ok = (z > 0.6) & (z < 3.5) & (lo > 0) & (hi - lo <= 0.05 * z)
        got = sample_depth(depth, pts, 0.6, 3.5, 0.05)
        np.testing.assert_array_equal(got, np.where(ok, z, 0.0))
        assert np.count_nonzero(got) >= 80


def test_rgbd_refinement_recovers_the_pose_from_a_perturbed_start() -> None:
    """Exact pixels and depths: Gauss-Newton with the disparity term lands on
    the true pose from 2 cm / 1 deg away."""
    from onboard.fastorb.pose import refine_pose

    rng = np.random.default_rng(9)
    T_true = se3_exp(_random_twist(rng, 0.1, 0.1))
    p_C = np.column_stack([rng.uniform(-1, 1, 50), rng.uniform(-0.8, 0.8, 50),
                           rng.uniform(1, 3, 50)])
    obj = (p_C - T_true[:3, 3]) @ T_true[:3, :3]  # world points
    img = p_C[:, :2] / p_C[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]
    start = se3_exp(np.array([0.01, -0.01, 0.005, 0.02, -0.01, 0.015])) @ T_true
    T = refine_pose(start, obj, img, K, 1.0, 10, 40.0 / p_C[:, 2], 40.0)
    np.testing.assert_allclose(T, T_true, atol=1e-7)
