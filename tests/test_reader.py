"""TUM-layout sequence reader: lists, association, camera, decoding, undistortion."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from onboard import NislamError
from onboard.core.camera import CameraIntrinsics, CameraModel
from onboard.core.messages import RgbdFrame
from sim_replay.tum import open_sequence
from sim_replay.tum_files import associate, load_camera, read_file_list

FR1_K = np.array([[517.3, 0.0, 318.6], [0.0, 516.5, 255.3], [0.0, 0.0, 1.0]])
FR1_DIST = np.array([0.2624, -0.9531, -0.0054, 0.0026, 1.1633])
SMALL_CAMERA_TOML = (
    "fx = 10.0\nfy = 10.0\ncx = 4.0\ncy = 3.0\nwidth = 8\nheight = 6\ndepth_scale = 1000.0\n"
)


def _reader_warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records
            if r.name == "sim_replay.tum" and r.levelno == logging.WARNING]


def _write_small_sequence(
    seq_dir: Path,
    rgb_times: list[float],
    depth_times: list[float],
    camera_toml: str | None = SMALL_CAMERA_TOML,
    size_wh: tuple[int, int] = (8, 6),
) -> Path:
    """A tiny sequence whose every listed file exists."""
    (seq_dir / "rgb").mkdir(parents=True)
    (seq_dir / "depth").mkdir()
    w, h = size_wh
    rgb_lines, depth_lines = ["# color images"], ["# depth maps"]
    for t in rgb_times:
        cv2.imwrite(str(seq_dir / "rgb" / f"{t:.6f}.png"), np.full((h, w, 3), 100, np.uint8))
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
    for t in depth_times:
        cv2.imwrite(str(seq_dir / "depth" / f"{t:.6f}.png"), np.full((h, w), 1500, np.uint16))
        depth_lines.append(f"{t:.6f} depth/{t:.6f}.png")
    (seq_dir / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (seq_dir / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    if camera_toml is not None:
        (seq_dir / "camera.toml").write_text(camera_toml)
    return seq_dir


def _present_stamps(seq_dir: Path) -> list[float]:
    return sorted(float(p.stem) for p in (seq_dir / "rgb").iterdir())


# --------------------------------------------------------------------------- fixtures from TUM


@pytest.mark.parametrize(
    ("name", "n_frames", "n_rgb", "n_depth", "fx"),
    [
        ("tum_fr1_desk_9frames", 9, 613, 595, 517.3),
        ("tum_fr3_office_16frames", 16, 2585, 2509, 535.4),
    ],
)
def test_damaged_fixture_yields_exactly_the_present_frames(
    shared_data, caplog, name, n_frames, n_rgb, n_depth, fx
):
    seq_dir = shared_data / "fixtures" / name
    caplog.set_level(logging.DEBUG, logger="sim_replay")
    seq = open_sequence(seq_dir)
    frames = list(seq)

    assert seq.n_rgb_entries == n_rgb and seq.n_depth_entries == n_depth
    assert len(seq) == n_frames == len(frames)
    np.testing.assert_allclose(seq.frame_times_s, _present_stamps(seq_dir), atol=1e-6)
    assert [f.t_s for f in frames] == list(seq.frame_times_s)
    # every listed file except the 2 * n_frames on disk is missing
    assert seq.skipped.missing_files == n_rgb + n_depth - 2 * n_frames
    assert seq.skipped.unreadable_files == 0
    assert seq.skipped.malformed_lines == 0
    assert seq.camera.fx == fx and seq.intrinsics.fx == fx
    for f in frames:
        assert isinstance(f, RgbdFrame)
        assert f.bgr.shape == (480, 640, 3) and f.bgr.dtype == np.uint8
        assert f.depth_m.shape == (480, 640) and f.depth_m.dtype == np.float32
        assert 0.3 < np.median(f.depth_m[f.depth_m > 0]) < 10.0  # metres, 5000 units/m
    warnings = _reader_warnings(caplog)
    assert len(warnings) == 1, warnings
    assert f"missing_files={n_rgb + n_depth - 2 * n_frames}" in warnings[0]


def test_fr1_rpy_opens_complete(shared_data, caplog):
    caplog.set_level(logging.INFO, logger="sim_replay")
    seq = open_sequence(shared_data / "tum_fr1_rpy")
    assert (seq.n_rgb_entries, seq.n_depth_entries) == (723, 722)
    # Paired within 20 ms on capture times: 722 (on the recorded stamps, as
    # TUM's associate.py pairs them, only 694: jitter pushes 28 pairs out).
    assert len(seq) == 722
    assert seq.skipped.missing_files == 0 and seq.skipped.malformed_lines == 0
    assert seq.skipped.unassociated == 723 + 722 - 2 * 722
    assert seq.stamps.frames_fitted == 723 and abs(seq.stamps.period_ms - 33.34) < 0.01
    assert 1.0 < seq.stamps.residual_rms_ms < 2.0
    assert len(open_sequence(shared_data / "tum_fr1_rpy", stamp_window_s=0.0)) == 694
    assert np.all(np.diff(seq.frame_times_s) > 0)
    assert seq.intrinsics == CameraIntrinsics(517.3, 516.5, 318.6, 255.3, 640, 480, 0.028)
    assert seq.groundtruth is not None and seq.attitude is None
    # unpaired entries are normal for TUM: no warning for a complete recording
    assert _reader_warnings(caplog) == []
    frames = seq.load_all(max_frames=3)
    assert [f.t_s for f in frames] == list(seq.frame_times_s[:3])


def test_groundtruth_bridges_the_130ms_gap_but_not_beyond_span(shared_data):
    seq = open_sequence(shared_data / "tum_fr1_rpy")
    gt_t = seq.groundtruth.t_s
    gaps = np.diff(gt_t)
    k = int(np.argmax(gaps))
    assert 0.12 < gaps[k] < 0.14
    t_mid = gt_t[k] + gaps[k] / 2
    p, q, valid = seq.groundtruth_at(np.array([t_mid, gt_t[0] - 0.01, gt_t[-1] + 0.01]))
    assert valid.tolist() == [True, False, False]
    assert np.isfinite(p[0]).all() and np.isclose(np.linalg.norm(q[0]), 1.0)
    assert np.isnan(p[1:]).all() and np.isnan(q[1:]).all()
    # the lead's rule is 200 ms; a caller asking for 100 ms loses the gap
    assert not seq.groundtruth_at([t_mid], max_gap_s=0.1)[2][0]


def test_groundtruth_over_300ms_gap_is_invalid(tmp_path):
    seq_dir = _write_small_sequence(tmp_path / "seq", [10.0], [10.001])
    gt = ["# timestamp tx ty tz qx qy qz qw"]
    for t in [9.9, 10.0, 10.1, 10.4, 10.5]:  # 300 ms gap between 10.1 and 10.4
        gt.append(f"{t:.4f} {t:.4f} 0 0 0 0 0 1")
    (seq_dir / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    seq = open_sequence(seq_dir)
    p, _q, valid = seq.groundtruth_at(np.array([10.05, 10.25, 10.45]))
    assert valid.tolist() == [True, False, True]
    assert np.isclose(p[0, 0], 10.05) and np.isclose(p[2, 0], 10.45)
    assert np.isnan(p[1]).all()


def test_groundtruth_at_without_groundtruth_raises(tmp_path):
    seq = open_sequence(_write_small_sequence(tmp_path / "seq", [1.0], [1.0]))
    with pytest.raises(NislamError, match="no groundtruth.txt"):
        seq.groundtruth_at([1.0])


# --------------------------------------------------------------------------- damaged copies


@pytest.fixture()
def fr3_copy(shared_data, tmp_path) -> Path:
    dst = tmp_path / "tum_fr3_office_16frames"
    shutil.copytree(shared_data / "fixtures" / "tum_fr3_office_16frames", dst)
    return dst


def test_damaged_files_and_lines_are_skipped_and_counted(fr3_copy, caplog):
    stamps = _present_stamps(fr3_copy)
    truncated = fr3_copy / "rgb" / f"{stamps[3]:.6f}.png"
    data = truncated.read_bytes()
    truncated.write_bytes(data[: len(data) * 2 // 3])
    not_png = sorted((fr3_copy / "depth").iterdir())[7]
    not_png.write_text("this is not an image\n")
    rgb_txt = fr3_copy / "rgb.txt"
    rgb_txt.write_text(
        "# color images\ngarbage header line\n"
        + rgb_txt.read_text()
        + "hello world\n1341847999.0\nnan rgb/nan.png\ninf rgb/inf.png\n\n"
    )
    caplog.set_level(logging.DEBUG, logger="sim_replay")

    seq = open_sequence(fr3_copy)
    assert seq.skipped.malformed_lines == 5
    assert len(seq) == 16  # both damaged files exist; decoding finds them out
    frames = list(seq)
    assert len(frames) == 14
    got = {round(f.t_s, 6) for f in frames}
    assert round(stamps[3], 6) not in got
    assert seq.skipped.unreadable_files == 2
    unreadable_warnings = [
        m for m in _reader_warnings(caplog) if "unreadable" in m and "of 16" in m
    ]
    assert len(unreadable_warnings) == 1
    assert "2 of 16 frames" in unreadable_warnings[0]
    debug = [r.getMessage() for r in caplog.records if r.levelno == logging.DEBUG]
    assert any(truncated.name in m and "truncated" in m for m in debug)
    assert any(not_png.name in m and "not a decodable image" in m for m in debug)
    # a second pass re-counts nothing: same files, same totals
    assert len(list(seq)) == 14 and seq.skipped.unreadable_files == 2


def test_truncated_png_rejected_even_if_decoder_would_accept(fr3_copy):
    # Drop only the IEND chunk: pixel data are all there (some OpenCV builds
    # decode it with a warning), but the file is incomplete and must not pass.
    path = fr3_copy / "depth" / sorted(p.name for p in (fr3_copy / "depth").iterdir())[0]
    data = path.read_bytes()
    assert data[-8:-4] == b"IEND"
    path.write_bytes(data[:-12])
    seq = open_sequence(fr3_copy)
    assert seq.read_frame(0) is None
    assert seq.read_frame(1) is not None
    assert seq.skipped.unreadable_files == 1


def test_wrong_image_size_is_unreadable(fr3_copy):
    path = sorted((fr3_copy / "rgb").iterdir())[0]
    cv2.imwrite(str(path), np.zeros((240, 320, 3), np.uint8))
    seq = open_sequence(fr3_copy)
    assert seq.read_frame(0) is None and seq.skipped.unreadable_files == 1


def test_list_naming_no_existing_file_raises(fr3_copy):
    (fr3_copy / "rgb.txt").write_text("# nothing here\n1341847980.722988 rgb/does_not_exist.png\n")
    with pytest.raises(NislamError, match="no usable frames") as err:
        open_sequence(fr3_copy)
    assert str(fr3_copy) in str(err.value) and "\n" not in str(err.value)


def test_missing_lists_raise(tmp_path):
    seq_dir = _write_small_sequence(tmp_path / "seq", [1.0], [1.0])
    (seq_dir / "depth.txt").unlink()
    with pytest.raises(NislamError, match="has no depth.txt"):
        open_sequence(seq_dir)
    with pytest.raises(NislamError, match="does not exist"):
        open_sequence(tmp_path / "nowhere")


# --------------------------------------------------------------------------- lists and association


def test_read_file_list_counts_malformed(tmp_path):
    p = tmp_path / "rgb.txt"
    p.write_text(
        "# comment\n\n#time, #image_file_name\n1.5 rgb/a.png\n1.6,rgb/b.png\n"
        "x rgb/c.png\n2.0\nnan rgb/d.png\n-inf rgb/e.png\n  3.25\trgb/f.png  \n"
    )
    entries, malformed = read_file_list(p)
    assert entries == [(1.5, "rgb/a.png"), (1.6, "rgb/b.png"), (3.25, "rgb/f.png")]
    assert malformed == 4


def test_associate_20ms_rule_greedy_one_to_one():
    rgb = [(1.000, "r1"), (2.000, "r2"), (3.000, "r3"), (4.000, "r4"), (4.012, "r5")]
    depth = [(1.010, "d1"), (2.025, "d2"), (2.990, "d3"), (3.005, "d4"), (4.010, "d5")]
    pairs = associate(rgb, depth, max_dt_s=0.02)
    named = [(rgb[i][1], depth[j][1]) for i, j in pairs]
    # r2-d2 is 25 ms apart: not associated; r3 takes the nearer d4 (5 ms) over
    # d3 (10 ms); d5 goes to r5 (2 ms) although r4 (10 ms) comes first.
    assert named == [("r1", "d1"), ("r3", "d4"), ("r5", "d5")]
    assert associate(rgb, depth, max_dt_s=0.03)[1] == (1, 1)
    assert associate([], depth) == []


def test_open_sequence_uses_20ms_association(tmp_path):
    seq_dir = _write_small_sequence(tmp_path / "seq", [1.0, 2.0, 3.0], [1.015, 2.025, 3.0])
    seq = open_sequence(seq_dir)
    np.testing.assert_allclose(seq.frame_times_s, [1.0, 3.0])  # frame time = rgb stamp
    assert seq.skipped.unassociated == 2  # r2 and d2
    assert len(open_sequence(seq_dir, max_assoc_dt_s=0.03)) == 3
    frame = next(iter(seq))
    assert frame.bgr.shape == (6, 8, 3)
    np.testing.assert_allclose(frame.depth_m, 1.5)  # 1500 units at 1000 per metre


# --------------------------------------------------------------------------- camera


def test_camera_toml_good(tmp_path):
    (tmp_path / "camera.toml").write_text(
        "fx = 585\nfy = 585.5\ncx = 320.0\ncy = 240.0   # pixels\nwidth = 640\nheight = 480\n"
        "depth_scale = 1000.0\ndistortion = [0.1, -0.2, 0.0, 0.0, 0.05]\n"
        "q_B_C_xyzw = [1.0, 1.0, 1.0, 1.0]\n"
    )
    cam = load_camera(tmp_path)
    assert cam == CameraModel(585.0, 585.5, 320.0, 240.0, 640, 480, 1000.0,
                              (0.1, -0.2, 0.0, 0.0, 0.05), (0.5, 0.5, 0.5, 0.5))
    assert cam.intrinsics() == CameraIntrinsics(585.0, 585.5, 320.0, 240.0, 640, 480)


@pytest.mark.parametrize(
    ("extra", "key"),
    [
        ("baseline = 0.05\n", "baseline"),
        ('width = "640"\n', "width"),
        ("width = 640.0\n", "width"),
        ("fx = true\n", "fx"),
        ('distortion = [0.1, "a"]\n', "distortion"),
        ("distortion = [0.1, 0.2, 0.3]\n", "distortion"),
        ("q_B_C_xyzw = [0, 0, 0]\n", "q_B_C_xyzw"),
        ("depth_scale = -1.0\n", "depth_scale"),
    ],
)
def test_camera_toml_bad_key_is_named(tmp_path, extra, key):
    base = (
        "fx = 585.0\nfy = 585.0\ncx = 320.0\ncy = 240.0\n"
        "width = 640\nheight = 480\ndepth_scale = 1000.0\n"
    )
    replaced = extra.split(" ")[0] + " "
    lines = [ln for ln in base.splitlines(keepends=True) if not ln.startswith(replaced)]
    (tmp_path / "camera.toml").write_text("".join(lines) + extra)
    with pytest.raises(NislamError, match=f"'{key}'") as err:
        load_camera(tmp_path)
    assert "\n" not in str(err.value)


def test_camera_toml_missing_key_and_syntax(tmp_path):
    (tmp_path / "camera.toml").write_text("fx = 585.0\n")
    with pytest.raises(NislamError, match="missing key 'fy'"):
        load_camera(tmp_path)
    (tmp_path / "camera.toml").write_text("fx = = 1\n")
    with pytest.raises(NislamError, match="not valid TOML"):
        load_camera(tmp_path)


@pytest.mark.parametrize(
    ("folder", "fx", "k1"),
    [
        ("tum_fr1_rpy", 517.3, 0.2624),
        ("rgbd_dataset_freiburg1_rpy", 517.3, 0.2624),
        ("rgbd_dataset_freiburg2_xyz", 520.9, 0.2312),
        ("TUM_FR3_office_16frames", 535.4, None),
        ("fr_2_desk", 520.9, 0.2312),
    ],
)
def test_camera_from_folder_name(tmp_path, folder, fx, k1):
    seq_dir = tmp_path / folder
    seq_dir.mkdir()
    cam = load_camera(seq_dir)
    assert cam.fx == fx and (cam.width, cam.height, cam.depth_scale) == (640, 480, 5000.0)
    assert (cam.distortion[0] if cam.distortion else None) == k1
    assert cam.q_B_C_xyzw == (0.0, 0.0, 0.0, 1.0)


@pytest.mark.parametrize("folder", ["my_drone_run", "frame12", "fr12_hall", "freiburg4"])
def test_camera_unknown_folder_name_raises(tmp_path, folder):
    seq_dir = tmp_path / folder
    seq_dir.mkdir()
    expected = "has no camera.toml and its name names no TUM freiburg 1/2/3"
    with pytest.raises(NislamError, match=expected):
        load_camera(seq_dir)


def test_camera_name_of_parent_does_not_count(tmp_path):
    seq_dir = tmp_path / "fr1_runs" / "run_007"
    seq_dir.mkdir(parents=True)
    with pytest.raises(NislamError):
        load_camera(seq_dir)


# --------------------------------------------------------------------------- undistortion


def test_undistortion_changes_fr1_but_not_fr3(shared_data):
    fr1 = open_sequence(shared_data / "fixtures" / "tum_fr1_desk_9frames")
    fr1_raw = open_sequence(shared_data / "fixtures" / "tum_fr1_desk_9frames", undistort=False)
    a, b = fr1.read_frame(0), fr1_raw.read_frame(0)
    assert np.mean(np.abs(a.bgr.astype(int) - b.bgr.astype(int))) > 2.0
    assert fr1.intrinsics == fr1_raw.intrinsics == fr1.camera.intrinsics()  # K kept
    # the black border where the distorted image has no pixels: no depth there
    assert np.all(a.depth_m[0:3, 0:3] == 0) and np.all(a.bgr[0:3, 0:3] == 0)
    # depth is looked up, never blended: every value exists in the raw image
    assert np.isin(np.unique(a.depth_m), np.unique(b.depth_m)).all()

    seq_dir = shared_data / "fixtures" / "tum_fr3_office_16frames"
    fr3 = open_sequence(seq_dir)
    frame = fr3.read_frame(0)
    name = sorted(p.name for p in (seq_dir / "rgb").iterdir())[0]  # frame times are capture times now
    raw_bgr = cv2.imread(str(seq_dir / "rgb" / name), cv2.IMREAD_COLOR)
    depth_name = sorted(p.name for p in (seq_dir / "depth").iterdir())[0]
    raw_depth = cv2.imread(str(seq_dir / "depth" / depth_name), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(frame.bgr, raw_bgr)
    assert np.array_equal(frame.depth_m, raw_depth.astype(np.float32) / np.float32(5000.0))


def test_corner_pixel_lands_where_undistort_points_says(tmp_path):
    seq_dir = _write_small_sequence(
        tmp_path / "synthetic_fr1", [1.0], [1.0], camera_toml=None, size_wh=(640, 480)
    )
    p_d = np.array([62.0, 52.0])  # distorted pixel near the top-left corner
    bgr = np.zeros((480, 640, 3), np.uint8)
    bgr[50:55, 60:65] = 255  # 5x5 blob centred on p_d
    cv2.imwrite(str(seq_dir / "rgb" / "1.000000.png"), bgr)
    depth = np.zeros((480, 640), np.uint16)
    depth[50:55, 60:65] = 7000
    cv2.imwrite(str(seq_dir / "depth" / "1.000000.png"), depth)

    frame = open_sequence(seq_dir).read_frame(0)
    p_u = cv2.undistortPoints(p_d.reshape(1, 1, 2), FR1_K, FR1_DIST, P=FR1_K).ravel()
    assert np.linalg.norm(p_u - p_d) > 5.0  # the test must notice a missing remap
    gray = frame.bgr[:, :, 0].astype(np.float64)
    ys, xs = np.nonzero(gray)
    weights = gray[ys, xs]
    centroid = np.array([np.average(xs, weights=weights), np.average(ys, weights=weights)])
    np.testing.assert_allclose(centroid, p_u, atol=0.5)
    dys, dxs = np.nonzero(frame.depth_m)
    np.testing.assert_allclose([dxs.mean(), dys.mean()], p_u, atol=1.0)
    assert set(np.unique(frame.depth_m)) == {0.0, np.float32(7000 / 5000)}
