"""The fleet as processes on 127.0.0.1: `nislam router`, two vehicles
(`nislam run` replaying a synthetic flight, one a zenoh peer, one a client,
each feeding a pymavlink peer process) and `nislam ground`. The router is
killed mid-flight and restarted: the vehicles fly on, the MAVLink feed keeps
its pace, and the ground station ends with every key frame of every vehicle.
"""

from __future__ import annotations

import json
import signal
import socket
import time
from pathlib import Path

import numpy as np
import pytest
from subproc import REPO, JsonLinesProcess, free_port, python_script

from onboard.outputs.ply import read_ply
from sim_replay.sim import SimOptions, simulate

NISLAM = REPO / ".venv" / "bin" / "nislam"
PEER = REPO / "tests" / "mavlink_peer.py"
WAIT_S = 120.0

# As tests/test_service.py: the shared machine pauses; the flight plays at a
# third of real time, so the 8 s flight lasts ~23 s and the outage fits in it.
PROFILE = """[mavlink]
stale_s = 3.0
[nislam]
max_coast_s = 3.0
[service]
stats_period_s = 1.0
replay_speed = 0.35
frame_timeout_s = 3.0
degraded_gap_s = 2.0
[zenoh]
status_period_s = 0.5
"""


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("fleet") / "circle"
    simulate("circle", out, SimOptions(seconds=8.0, width=320, height=240), progress=False)
    return out


def wait_text(proc: JsonLinesProcess, needle: str, what: str) -> None:
    deadline = time.monotonic() + WAIT_S
    while not any(needle in line for line in proc.text):
        assert proc.proc.poll() is None, f"{what}: exited {proc.proc.returncode}: {proc.stderr}"
        assert time.monotonic() < deadline, f"{what}: not within {WAIT_S} s"
        time.sleep(0.05)


def odometry_times(peer: JsonLinesProcess) -> np.ndarray:
    return np.array([m["t"] for m in peer.lines if m.get("mavpackettype") == "ODOMETRY"])


# The router and the ground station run on other machines in the field; here
# they share 2 cores with the vehicles, so they run at the lowest CPU priority:
# a router starting (about 1 s of CPU to import and load the config) must not
# be what delays a vehicle's MAVLink feed in this test.
NICE = ["nice", "-n", "19"]


def start_router(port: int) -> JsonLinesProcess:
    router = JsonLinesProcess([*NICE, str(NISLAM), "router", "--listen", f"tcp/127.0.0.1:{port}"])
    wait_text(router, "listening on", "router up")
    return router


def max_gaps_s(t: np.ndarray, lo: float, hi: float) -> tuple[float, float]:
    """Longest gap between successive ODOMETRY inside [lo, hi] and outside it
    (gaps that straddle a bound count as inside)."""
    gaps = np.diff(t)
    inside = (t[1:] >= lo) & (t[:-1] <= hi)
    return float(gaps[inside].max(initial=0.0)), float(gaps[~inside].max(initial=0.0))


def test_router_killed_and_restarted_mid_flight(flight: Path, tmp_path: Path) -> None:
    port = free_port(socket.SOCK_STREAM)
    ep = f"tcp/127.0.0.1:{port}"
    config = tmp_path / "profile.toml"
    config.write_text(PROFILE)
    procs: list[JsonLinesProcess] = []
    router = start_router(port)
    ground = JsonLinesProcess([*NICE, str(NISLAM), "ground", "--connect", ep, "--out",
                               str(tmp_path / "ground")])
    procs += [router, ground]
    vehicles: dict[str, JsonLinesProcess] = {}
    peers: dict[str, JsonLinesProcess] = {}
    try:
        for vid, mode in (("v1", ()), ("v2", ("--zenoh-mode", "client"))):
            mav = free_port()
            peers[vid] = JsonLinesProcess(python_script(PEER, f"udpin:127.0.0.1:{mav}"))
            peers[vid].wait_for(lambda ls: any(m.get("ready") for m in ls), WAIT_S, "peer")
            vehicles[vid] = JsonLinesProcess([
                str(NISLAM), "run", "--replay", str(flight), "--config", str(config),
                "--vehicle", vid, "--zenoh-connect", ep, *mode,
                "--mavlink", f"udpout:127.0.0.1:{mav}", "--out", str(tmp_path / vid)])
        procs += [*peers.values(), *vehicles.values()]

        def poses_each(n: int) -> None:
            for vid, peer in peers.items():
                peer.wait_for(lambda ls: sum(m.get("mavpackettype") == "ODOMETRY" for m in ls)
                              >= n, WAIT_S, f"{n} poses from {vid}")

        poses_each(40)
        router.stop(signal.SIGKILL)
        t_kill = time.monotonic()
        at_kill = min(len(odometry_times(p)) for p in peers.values())
        poses_each(at_kill + 30)  # the vehicles fly on without the router
        router = start_router(port)
        procs.append(router)
        t_back = time.monotonic()
        for vid, v in vehicles.items():
            assert v.proc.wait(WAIT_S) == 0, f"{vid}: {v.stderr[-2000:]}"
            assert v.stop() == 0
        # At nice 19 beside other jobs the ground station's exit (maps settled,
        # PLYs and the matplotlib plot written: ~3 s of CPU) took over 20 s of
        # wall time once (py-spy: in savefig when SIGKILLed): it is given as
        # long as the vehicles; its exit status is what is checked.
        assert ground.stop(timeout=WAIT_S) == 0, ground.stderr[-2000:]
    finally:
        for p in procs:
            p.stop()

    fleet = json.loads((tmp_path / "ground" / "fleet.json").read_text())["vehicles"]
    assert sorted(fleet) == ["v1", "v2"], fleet.keys()
    for vid in ("v1", "v2"):
        run = json.loads((tmp_path / vid / "run.json").read_text())
        got = fleet[vid]
        assert run["keyframes_published"] >= 2
        assert got["keyframes"] == run["keyframes_published"], (vid, got, run)
        # Ids and content: the CRC-32 of each key frame's message on both sides.
        assert got["keyframe_crc32"] == run["keyframe_crc32"], vid
        assert got["restarts"] == 0 and got["poses"] > 0 and got["last_state"] == "tracking"
        xyz, _ = read_ply(tmp_path / "ground" / f"{vid}.ply")
        assert len(xyz) == got["map_points"] == run["outputs"]["zenoh"]["map_points"]
        # The MAVLink feed never waited for zenoh: no longer gap while the
        # router was down (and the sessions reconnecting) than in the rest.
        t = odometry_times(peers[vid])
        during, outside = max_gaps_s(t, t_kill, t_back + 3.0)
        print(f"{vid}: ODOMETRY {len(t)}, longest gap during the outage {during * 1e3:.0f} ms, "
              f"outside {outside * 1e3:.0f} ms; key frames {got['keyframes']}, map fetches "
              f"{got['map_fetches']}")
        # This machine's pauses reach 0.3-0.4 s anywhere in a run (both vehicles
        # at once, during or outside the outage); a feed held up by zenoh (a
        # blocking open or put, a reconnection) would stall for 0.5-5 s.
        assert during <= max(1.5 * outside, 0.3) + 0.05, (vid, during, outside)
    assert (tmp_path / "ground" / "fleet.png").stat().st_size > 0
