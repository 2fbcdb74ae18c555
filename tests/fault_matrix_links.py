"""Fault-matrix rows (tests/fault_matrix.py) for a link and for stamps:

- the zenoh router gone and back: a real `nislam router` process killed and
  restarted, the real ZenohOutput as a client, a ground subscriber through the
  router;
- the AHRS's stamps jumping ahead or back by 3 s while the camera's do not:
  the real myAHRS+ driver on the simulated device, its samples shifted on
  their way into the real AttitudeBuffer (live: checked against the clock).
"""

from __future__ import annotations

import signal
import socket
import threading
import time
from pathlib import Path

import numpy as np
from fault_matrix import DEVICE, WAIT_S, AhrsDevice, Lines, Row, Stamps, _has
from subproc import REPO, JsonLinesProcess, free_port

from onboard.core.attitude import AttitudeBuffer, AttitudeSample
from onboard.core.messages import TrackResult, TrackState

NISLAM = REPO / ".venv" / "bin" / "nislam"


def tracked(t: float) -> TrackResult:
    return TrackResult(
        t_s=t, state=TrackState.TRACKING, trusted=True, p_W_m=np.zeros(3), R_W_C=np.eye(3),
        pose_var=np.full(6, 1e-4), quality=80, psr=20.0, keyframe_id=1, new_keyframe=False,
        reset_counter=0, lost_reason=None, shift_cells=(0.0, 0.0), tz_m=0.0, res_m=0.01,
        rotation_residual_rad=np.zeros(3), attitude_offset_s=0.0, matched_cells=100)


def start_router(port: int) -> tuple[JsonLinesProcess, float]:
    """`nislam router` on 127.0.0.1:port; the monotonic time its port first
    accepts a connection (its "listening on" line may be read later than
    the vehicles reconnect)."""
    router = JsonLinesProcess([str(NISLAM), "router", "--listen", f"tcp/127.0.0.1:{port}"])
    deadline = time.monotonic() + WAIT_S
    while True:
        assert router.proc.poll() is None, f"router exited: {router.stderr}"
        assert time.monotonic() < deadline, "router not up"
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
            return router, time.monotonic()
        except OSError:
            time.sleep(0.005)


def zenoh_router(lines: Lines, tmp: Path) -> Row:
    import zenoh

    from onboard.outputs.settings import ZenohConfig
    from onboard.outputs.zenoh_out import ZenohOutput, key_prefix, session_config

    port = free_port(socket.SOCK_STREAM)
    endpoint = f"tcp/127.0.0.1:{port}"
    cfg = ZenohConfig(enabled=True, vehicle="fm", mode="client", connect=(endpoint,),
                      status_period_s=0.2)
    router, _ = start_router(port)
    out = ZenohOutput(cfg)
    ground = zenoh.open(session_config(cfg))  # a ground station: another client
    heard = Stamps()
    sub = ground.declare_subscriber(f"{key_prefix('fm')}/pose",
                                    lambda s: heard.add(time.monotonic()))
    stop = threading.Event()

    def feed() -> None:  # the loop's poses at 20 Hz
        t = 0.0
        while not stop.wait(0.05):
            t += 0.05
            out.publish(tracked(t))

    feeder = threading.Thread(target=feed, daemon=True)
    feeder.start()
    try:
        heard.wait("no pose reached the ground through the router", n=5)
        assert lines.count(_has("zenoh router")) == 0
        router.stop(signal.SIGKILL)
        t_inject = time.monotonic()
        t_warn = lines.wait(_has("zenoh router", ": no device"), t_inject)
        router, t_clear = start_router(port)
        t_rec = lines.wait(_has("zenoh router", "recovered"), t_warn)
        # poses heard at the ground while we said the router was away: must be none
        passed = heard.count(t_warn, t_clear)
        # and poses reach the ground again
        t_ground = heard.wait("no pose reached the ground after the restart", after=t_clear)
        reminders = lines.count(_has("zenoh router", "still"), t_inject)
        assert reminders == 0 and lines.count(_has("zenoh router", ": no device"), t_inject) == 1
        return Row("zenoh router gone", "the session's routers, polled every 0.25 s",
                   t_warn - t_inject, max(t_rec - t_clear, 0.0), passed, "none",
                   f"poses at the ground again {t_ground - t_clear:.2f} s after the router "
                   "listens; poses put meanwhile are lost on the wire (no backlog)")
    finally:
        stop.set()
        feeder.join(5)
        sub.undeclare()
        ground.close()
        out.close(5)
        router.stop(signal.SIGKILL)


def ahrs_time_jump(direction: str, lines: Lines, tmp: Path) -> Row:
    from drivers.myahrs import MyAhrsDriver

    assert DEVICE.exists()
    link = tmp / f"myahrs_jump_{direction}"
    dev = AhrsDevice(link)
    dev.expect("plugged")
    buf = AttitudeBuffer(now_ns=time.monotonic_ns, label="myAHRS+")
    shift = {"ns": 0}
    jump_ns = int((3.0 if direction == "ahead" else -3.0) * 1e9)

    def sink(sample: AttitudeSample) -> None:  # the AHRS's stamps, jumped or not
        buf.push(AttitudeSample(sample.t_ns + shift["ns"], sample.q_W_B_xyzw))

    drv = MyAhrsDriver(str(link), sink, silence_s=0.5, reopen_after_s=3.0,
                       reconnect_min_s=0.05, reconnect_max_s=0.2)
    drv.start()
    try:
        assert buf.wait_for_samples(20, WAIT_S)
        t_inject = time.monotonic()
        shift["ns"] = jump_ns
        t_warn = lines.wait(_has("myAHRS+ stamps", ": bad data"), t_inject)
        stored = buf.stats.pushed
        time.sleep(1.0)  # the jump lasts a while
        stored = buf.stats.pushed - stored
        t_clear = time.monotonic()
        shift["ns"] = 0
        t_rec = lines.wait(_has("myAHRS+ stamps", "recovered"), t_warn)
        assert buf.wait_for_samples(buf.stats.pushed + 5, WAIT_S)
        # frames captured while the stamps were wrong (30 Hz): none may get an attitude
        frames = np.arange(t_warn, t_clear, 1 / 30)
        attituded = sum(buf.rotation_at(t) is not None for t in frames)
        told = lines.count(_has("myAHRS+ stamps", ": bad data"), t_inject)
        assert told == 1, f"{told} warning lines for one jump"
        return Row(f"AHRS time jump {direction} (3 s)",
                   "each sample's stamp against the clock, jump_s 2 s", t_warn - t_inject,
                   max(t_rec - t_clear, 0.0), stored + attituded, "none",
                   f"samples stored + frames given an attitude while wrong "
                   f"({len(frames)} frames, {buf.stats.rejected_time_jump} samples dropped)")
    finally:
        drv.stop(10)
        dev.close()
