"""zenoh publishing: the key-frame encoding, the pose message, and the
publisher with `nislam listen` as the subscriber in another process."""

from __future__ import annotations

import dataclasses
import json
import signal
import socket
import struct
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh
from fake_results import keyframe, track_result
from subproc import REPO, JsonLinesProcess, free_port

from onboard.core.messages import KeyframeCloud
from onboard.outputs.listen import MapListener
from onboard.outputs.mapcodec import MapCodecError, MapKeyframe, decode_keyframe, encode_keyframe
from onboard.outputs.ply import read_ply
from onboard.outputs.settings import ZenohConfig
from onboard.outputs.zenoh_out import ZenohOutput, pose_message, session_config

NISLAM = REPO / ".venv" / "bin" / "nislam"
DT = 1.0 / 30.0
WAIT_S = 60.0


def endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"


def same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


# --------------------------------------------------------------------------- encoding


@pytest.mark.parametrize("fill", [0.0, 0.3, 1.0])
def test_keyframe_round_trip_is_bit_exact(fill: float) -> None:
    kf = keyframe(7, shape=(45, 61), fill=fill)  # odd sizes: the mask's last byte is partial
    data = encode_keyframe(kf)
    got = decode_keyframe(data)
    xyz, rgb = kf.points()
    gxyz, grgb = got.points()
    assert same_bits(gxyz, xyz) and same_bits(grgb, rgb)
    assert (got.keyframe_id, got.t_s, got.res_m) == (7, kf.t_s, kf.res_m)
    assert same_bits(got.p_W_m, kf.p_W_m) and same_bits(got.R_W_C, kf.R_W_C)
    assert encode_keyframe(got) == data
    n = len(xyz)
    assert len(data) == 136 + (45 * 61 + 7) // 8 + 7 * n  # about 7 bytes per point


def test_keyframe_layout_matches_the_documentation() -> None:
    kf = keyframe(3, shape=(8, 16))
    data = encode_keyframe(kf)
    magic, version, dsize, kid, h, w, n = struct.unpack_from("<4sBB2xiHHI", data)
    assert (magic, version, dsize, kid, h, w) == (b"NSKF", 1, 4, 3, 8, 16)
    assert struct.unpack_from("<d", data, 24)[0] == kf.t_s
    assert struct.unpack_from("<3d", data, 32) == tuple(kf.p_W_m)
    assert struct.unpack_from("<9d", data, 56) == tuple(kf.R_W_C.reshape(9))
    assert struct.unpack_from("<d", data, 128)[0] == kf.res_m
    mask = np.unpackbits(np.frombuffer(data, np.uint8, 16, 136), bitorder="little")
    assert np.array_equal(mask.reshape(8, 16), kf.depth_m > 0) and mask.sum() == n
    depth = np.frombuffer(data, "<f4", n, 152)
    assert np.array_equal(depth, kf.depth_m[kf.depth_m > 0])
    rgb = np.frombuffer(data, np.uint8, 3 * n, 152 + 4 * n).reshape(n, 3)
    assert np.array_equal(rgb, kf.points()[1])


def test_float64_depth_and_a_real_tracker_key_frame_round_trip(shared_data: Path) -> None:
    kf = keyframe(1)
    kf64 = KeyframeCloud(kf.keyframe_id, kf.t_s, kf.p_W_m, kf.R_W_C, kf.res_m,
                         kf.depth_m.astype(np.float64), kf.gray, kf.bgr)
    assert same_bits(decode_keyframe(encode_keyframe(kf64)).points()[0], kf64.points()[0])

    from onboard.app.config import Config
    from onboard.app.replay import track_sequence
    from onboard.fusion.registry import make_tracker
    from sim_replay.attitude import AttitudeErrorModel, attitude_for_replay
    from sim_replay.tum import open_sequence

    seq = open_sequence(shared_data / "fixtures" / "tum_fr3_office_16frames", 0.02, True)
    attitude, _ = attitude_for_replay(seq, AttitudeErrorModel(), 0.2)
    tracker = make_tracker("nislam", seq.intrinsics, Config())
    log = track_sequence(tracker, seq, attitude, None, progress=False)
    assert log.clouds
    for cloud in log.clouds.values():
        xyz, rgb = cloud.points()
        gxyz, grgb = decode_keyframe(encode_keyframe(cloud)).points()
        assert same_bits(gxyz, xyz) and same_bits(grgb, rgb)


def test_damaged_keyframe_messages_are_refused() -> None:
    data = encode_keyframe(keyframe(2, shape=(10, 10)))
    for bad in (data[:100], data[:-1], data + b"\0", b"XXXX" + data[4:],
                data[:4] + b"\x02" + data[5:]):
        with pytest.raises(MapCodecError):
            decode_keyframe(bad)
    flipped = bytearray(data)
    flipped[136] ^= 0xFF  # mask no longer agrees with the point count
    with pytest.raises(MapCodecError):
        decode_keyframe(bytes(flipped))


def test_pose_message_fields() -> None:
    r = track_result(12.5, [1.0, 2.0, 3.0], quality=77, reset_counter=2, keyframe_id=4)
    m = json.loads(json.dumps(pose_message(r, 9), allow_nan=False))
    assert m["seq"] == 9 and m["t_s"] == 12.5 and m["state"] == "tracking" and m["trusted"]
    assert m["p_W_m"] == [1.0, 2.0, 3.0] and m["q_W_C_xyzw"] == [0.0, 0.0, 0.0, 1.0]
    assert (m["quality"], m["reset_counter"], m["keyframe_id"]) == (77, 2, 4)
    lost = pose_message(track_result(13.0, trusted=False, lost_reason="no attitude"), 10)
    assert lost["p_W_m"] is None and lost["pose_var"] is None and lost["psr"] is None
    assert (lost["quality"], lost["lost_reason"], lost["state"]) == (-1, "no attitude", "lost")
    json.dumps(lost, allow_nan=False)


def test_session_config_defaults_to_no_multicast() -> None:
    conf = session_config(ZenohConfig(connect=("tcp/127.0.0.1:7447",)))
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(conf.get_json("mode")) == "peer"
    conf = session_config(ZenohConfig(), mode="client", listen=("tcp/127.0.0.1:1",))
    assert json.loads(conf.get_json("mode")) == "client"
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:1"]


# --------------------------------------------------------------------------- publishing


def wait_until(pred, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < deadline, f"{what} not met within {timeout} s"
        time.sleep(0.02)


def test_publisher_keeps_running_without_a_peer() -> None:
    cfg = ZenohConfig(vehicle="alone", connect=(endpoint(),), queue_frames=64,
                      status_period_s=0.05)
    with ZenohOutput(cfg) as out:
        for i in range(300):
            fin = (keyframe(i // 30, shape=(60, 80)),) if i % 30 == 29 else ()
            out.publish(track_result(i * DT, [0.01 * i, 0, 0], finished=fin))
        wait_until(lambda: out.stats()["map_keyframes"] == 10, WAIT_S, "key frames stored")
        # Every pose published or dropped from the full queue, counted.
        wait_until(lambda: out.stats()["frames"] + out.stats()["dropped_poses"] == 300, WAIT_S,
                   "poses handled")
        stats = out.stats()
        assert stats["errors"] == 0 and stats["map_points"] > 0
        assert stats["poses_published"] == stats["frames"]
        t = time.perf_counter()
    print(f"close took {time.perf_counter() - t:.2f} s")  # it returned: it does not hang


class _Undeclarable:
    def undeclare(self) -> None:
        pass


class StuckSession:
    """The part of a zenoh.Session that ZenohOutput uses, on a congested link:
    every put (congestion control BLOCK) hangs until `release` is set."""

    def __init__(self) -> None:
        self.entered = threading.Event()  # a put is hanging
        self.release = threading.Event()
        self.puts: dict[str, list] = {}

    def put(self, key: str, payload, **kwargs) -> None:
        self.entered.set()
        self.release.wait(WAIT_S)
        self.puts.setdefault(key, []).append(payload)

    def declare_publisher(self, key: str, **kwargs) -> StuckPublisher:
        return StuckPublisher(self, key)

    def declare_queryable(self, key: str, callback) -> _Undeclarable:
        return _Undeclarable()

    def liveliness(self) -> StuckSession:
        return self

    def declare_token(self, key: str) -> _Undeclarable:
        return _Undeclarable()


class StuckPublisher(_Undeclarable):
    def __init__(self, session: StuckSession, key: str) -> None:
        self.session = session
        self.key = key

    def put(self, payload) -> None:
        self.session.put(self.key, payload)

    def declare_matching_listener(self, callback) -> _Undeclarable:
        return _Undeclarable()


def test_publish_never_waits_for_the_network() -> None:
    """publish() returns while both publishing threads hang in a put: the
    loop never waits on the network; what the full queue drops is counted."""
    session = StuckSession()
    out = ZenohOutput(ZenohConfig(vehicle="stuck", queue_frames=8, status_period_s=WAIT_S),
                      session=session)
    try:
        # The pose thread's first status put hangs before anything is published.
        assert session.entered.wait(WAIT_S)
        done = threading.Event()

        def publish_all() -> None:
            for i in range(100):
                out.publish(track_result(i * DT, [0.0, 0.0, 0.0],
                                         finished=(keyframe(i, shape=(4, 4)),)))
            done.set()

        threading.Thread(target=publish_all, daemon=True).start()
        assert done.wait(WAIT_S)  # would time out if publish() waited for the network
        assert not session.release.is_set()  # ... which still hangs
        assert out.stats()["dropped_poses"] == 100 - 8  # the queue keeps the newest 8
    finally:
        session.release.set()
        out.close(WAIT_S)
    stats = out.stats()
    assert stats["frames"] + stats["dropped_poses"] == 100
    poses = [json.loads(p) for p in session.puts["nislam/stuck/pose"]]
    assert [m["t_s"] for m in poses] == [i * DT for i in range(92, 100)]
    assert len(session.puts) == 2 + 100  # status, pose and every key frame
    assert stats["dropped_keyframes"] == 0 and stats["map_keyframes"] == 100


def test_queryable_answers_per_key_frame() -> None:
    ep = endpoint()
    with ZenohOutput(ZenohConfig(vehicle="q1", listen=(ep,))) as out:
        kfs = [keyframe(i, shape=(20, 30)) for i in range(3)]
        for kf in kfs:
            out.publish_keyframe(kf)
        wait_until(lambda: out.stats()["map_keyframes"] == 3, WAIT_S, "key frames stored")
        with zenoh.open(session_config(ZenohConfig(connect=(ep,)))) as session:
            listener = MapListener(session, "q1")
            deadline = time.monotonic() + WAIT_S
            got: list[MapKeyframe] = []
            while len(got) < 3 and time.monotonic() < deadline:
                got = listener.fetch_map(10.0)  # the peers may still be connecting
            assert sorted(kf.keyframe_id for kf in got) == [0, 1, 2]
            one = list(session.get("nislam/q1/map/keyframe/1", timeout=10.0))
            assert [str(r.ok.key_expr) for r in one] == ["nislam/q1/map/keyframe/1"]
            assert same_bits(decode_keyframe(one[0].ok.payload.to_bytes()).points()[0],
                             kfs[1].points()[0])
            listener.close()


def test_a_moved_key_frame_is_re_published_at_its_new_pose() -> None:
    """A loop closure moved key frame 1 (TrackResult.moved_keyframes): the map
    then holds and serves it at the new pose with the same cells; key frame
    0 is untouched, and a move of a key frame never held is ignored."""
    ep = endpoint()
    with ZenohOutput(ZenohConfig(vehicle="m1", listen=(ep,))) as out:
        kfs = [keyframe(i, shape=(20, 30)) for i in range(2)]
        for kf in kfs:
            out.publish_keyframe(kf)
        wait_until(lambda: out.stats()["map_keyframes"] == 2, WAIT_S, "key frames stored")
        R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
        moved = dataclasses.replace(track_result(1.0, [0, 0, 0]),
                                    moved_keyframes=((1, np.array([0.5, 0.0, 0.1]), R),
                                                     (9, np.zeros(3), np.eye(3))))
        out.publish(moved)
        with zenoh.open(session_config(ZenohConfig(connect=(ep,)))) as session:
            def pose_of(kf_id: int) -> MapKeyframe | None:
                got = list(session.get(f"nislam/m1/map/keyframe/{kf_id}", timeout=10.0))
                return decode_keyframe(got[0].ok.payload.to_bytes()) if got else None

            def moved_yet() -> bool:
                k = pose_of(1)
                return k is not None and np.allclose(k.p_W_m, [0.5, 0.0, 0.1])

            wait_until(moved_yet, WAIT_S, "key frame 1 moved")
            k1, k0 = pose_of(1), pose_of(0)
            assert np.allclose(k1.R_W_C, R) and np.array_equal(k1.mask, kfs[1].depth_m > 0)
            assert np.allclose(k0.p_W_m, kfs[0].p_W_m) and np.allclose(k0.R_W_C, kfs[0].R_W_C)
        assert out.stats()["map_keyframes"] == 2


def start_listener(ep: str, vehicle: str, out: Path) -> JsonLinesProcess:
    proc = JsonLinesProcess([str(NISLAM), "listen", "--connect", ep, "--vehicle", vehicle,
                             "--json", "--out", str(out)])
    proc.wait_for(lambda lines: any(m["type"] == "map" for m in lines), WAIT_S, "listener up")
    return proc


def wait_for_map_subscriber(session: zenoh.Session, vehicle: str, timeout_s: float) -> bool:
    """True once `session` knows a subscriber of the vehicle's key frames (the
    listener declares it next to the pose one; the publisher's
    wait_for_subscribers sees only the pose's). A probe publisher on the key
    frames' key space, never put on, tells through its matching status."""
    matched = threading.Event()
    probe = session.declare_publisher(f"nislam/{vehicle}/map/keyframe/*")
    watch = probe.declare_matching_listener(lambda st: matched.set() if st.matching else None)
    try:
        return probe.matching_status.matching or matched.wait(timeout_s)
    finally:
        watch.undeclare()
        probe.undeclare()


def test_poses_and_key_frames_reach_a_subscriber_in_another_process(tmp_path: Path) -> None:
    ep = endpoint()
    cfg = ZenohConfig(vehicle="v1", listen=(ep,), queue_frames=1000, status_period_s=0.2)
    kfs = [keyframe(i, shape=(48, 64)) for i in range(4)]
    with ZenohOutput(cfg) as out:
        listener = start_listener(ep, "v1", tmp_path / "map.ply")
        try:
            assert out.wait_for_subscribers(WAIT_S)
            assert wait_for_map_subscriber(out.session, "v1", WAIT_S)
            t0 = 5000.0
            for i in range(150):
                fin = (kfs[i // 40],) if i % 40 == 39 else ()
                trusted = not 60 <= i < 63
                out.publish(track_result(t0 + i * DT, [0.01 * i, 0.5, -0.2], trusted=trusted,
                                         finished=fin, lost_reason="peak too weak"))
            out.publish_keyframe(kfs[3])  # tracker.finish() at the end of a run
            listener.wait_for(lambda lines: sum(m["type"] == "pose" for m in lines) >= 150
                              and sum(m["type"] == "keyframe" for m in lines) >= 4, WAIT_S,
                              "every pose and key frame")
            # A status made after the last key frame was stored (statuses go
            # out every 0.2 s; one made before it still says 3).
            listener.wait_for(lambda lines: any(m["type"] == "status" and m["frames"] == 150
                                                and m["map_keyframes"] == 4 for m in lines),
                              WAIT_S, "a status of the whole run")
        finally:
            rc = listener.stop(signal.SIGTERM, WAIT_S)
    assert rc == 0, listener.stderr
    poses = listener.of_type("pose")
    assert [m["seq"] for m in poses] == list(range(150))  # all, in order
    assert [m["t_s"] for m in poses] == [5000.0 + i * DT for i in range(150)]
    assert [m["trusted"] for m in poses] == [not 60 <= i < 63 for i in range(150)]
    assert poses[10]["p_W_m"] == [0.1, 0.5, -0.2]
    assert poses[61]["p_W_m"] is None and poses[61]["quality"] == -1
    status = [m for m in listener.of_type("status")
              if m["frames"] == 150 and m["map_keyframes"] == 4][-1]
    assert (status["frames_lost"], status["frames_tracked"], status["dropped_poses"]) == (3, 147, 0)

    events = listener.of_type("keyframe")
    assert [e["keyframe_id"] for e in events] == [0, 1, 2, 3]
    for e, kf in zip(events, kfs):  # exact floats through JSON
        assert e["p_W_m"] == kf.p_W_m.tolist() and e["R_W_C"] == kf.R_W_C.tolist()
        assert (e["t_s"], e["res_m"], e["points"]) == (kf.t_s, kf.res_m, len(kf.points()[0]))
    # the map written on exit is the published clouds, bit for bit
    xyz, rgb = read_ply(tmp_path / "map.ply")
    assert same_bits(xyz, np.concatenate([kf.points()[0] for kf in kfs]))
    assert same_bits(rgb, np.concatenate([kf.points()[1] for kf in kfs]))
    saved = listener.of_type("saved")
    assert saved and saved[0]["keyframes"] == 4


def test_late_subscriber_gets_the_whole_map(tmp_path: Path) -> None:
    ep = endpoint()
    kfs = [keyframe(i, shape=(40, 50), seed=5) for i in range(6)]
    with ZenohOutput(ZenohConfig(vehicle="late", listen=(ep,), status_period_s=0.2)) as out:
        for i, kf in enumerate(kfs[:5]):
            out.publish(track_result(i * DT, [0.0, 0.0, 0.0], finished=(kf,)))
        wait_until(lambda: out.stats()["map_keyframes"] == 5, WAIT_S, "map stored")
        listener = start_listener(ep, "late", tmp_path / "late.ply")
        try:
            fetched = listener.of_type("map")[0]
            assert (fetched["fetched"], fetched["points"]) == (
                5, sum(len(k.points()[0]) for k in kfs[:5]))
            assert wait_for_map_subscriber(out.session, "late", WAIT_S)
            out.publish_keyframe(kfs[5])  # and it keeps the map up to date
            listener.wait_for(lambda lines: any(m["type"] == "keyframe" and m["keyframe_id"] == 5
                                                for m in lines), WAIT_S, "live key frame")
        finally:
            rc = listener.stop(signal.SIGINT, WAIT_S)
    assert rc == 0, listener.stderr
    xyz, rgb = read_ply(tmp_path / "late.ply")
    assert same_bits(xyz, np.concatenate([kf.points()[0] for kf in kfs]))
    assert same_bits(rgb, np.concatenate([kf.points()[1] for kf in kfs]))


def test_listen_refuses_a_bad_vehicle_id_in_one_line() -> None:
    import subprocess

    proc = subprocess.run([str(NISLAM), "listen", "--vehicle", "a/b"], capture_output=True,
                          text=True, timeout=WAIT_S)
    assert proc.returncode == 1
    assert proc.stderr.strip().count("\n") == 0 and "zenoh.vehicle" in proc.stderr
