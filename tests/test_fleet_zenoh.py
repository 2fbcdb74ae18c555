"""The fleet on real zenoh sessions in one process: a router (zenoh's router
mode), vehicles (ZenohOutput as clients) and the ground station; mutual TLS
and the access-control list with certificates made by `openssl`."""

from __future__ import annotations

import json
import socket
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
import zenoh
from fake_results import keyframe, track_result
from fleet_pki import make_ca, make_cert
from subproc import free_port

from onboard import NislamError
from onboard.outputs.fleet_files import write_fleet
from onboard.outputs.ground import GroundStation
from onboard.outputs.mapcodec import map_digest
from onboard.outputs.router import access_control, router_config, router_json
from onboard.outputs.settings import RouterConfig, ZenohConfig
from onboard.outputs.zenoh_messages import RateLimit
from onboard.outputs.zenoh_out import ZenohOutput
from onboard.outputs.zenoh_session import open_session, session_config

WAIT_S = 30.0


def endpoint(proto: str = "tcp") -> str:
    return f"{proto}/127.0.0.1:{free_port(socket.SOCK_STREAM)}"


@contextmanager
def router(cfg: RouterConfig) -> Iterator[zenoh.Session]:
    s = open_session(router_config(cfg))
    try:
        yield s
    finally:
        s.close()


@contextmanager
def ground(cfg: ZenohConfig) -> Iterator[GroundStation]:
    session = open_session(session_config(cfg, mode="client"))
    station = GroundStation(session, fetch_timeout_s=5.0)
    try:
        yield station
    finally:
        station.close()
        session.close()


def pump(station: GroundStation, pred: Callable[[], bool], what: str) -> None:
    """Handle the station's events until pred() holds."""
    deadline = time.monotonic() + WAIT_S
    while not pred():
        assert time.monotonic() < deadline, f"{what}: not within {WAIT_S} s"
        station.step(0.05)


def wait_until(pred: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + WAIT_S
    while not pred():
        assert time.monotonic() < deadline, f"{what}: not within {WAIT_S} s"
        time.sleep(0.01)


def fly(out: ZenohOutput, n_poses: int, keyframe_ids: list[int], seed: int,
        reset_counter: int = 0) -> None:
    """n_poses results; the key frames finish with the first one."""
    kfs = tuple(keyframe(k, shape=(30, 40), seed=seed) for k in keyframe_ids)
    for i in range(n_poses):
        out.publish(track_result(i / 30.0, [0.1 * i, 0.0, 0.0], reset_counter=reset_counter,
                                 finished=kfs if i == 0 else ()))
    wait_until(lambda: out.stats()["keyframes_published"] == len(keyframe_ids), "key frames held")


# --------------------------------------------------------------------------- topology


def test_late_join_and_a_restarted_vehicle_stays_one_vehicle(tmp_path: Path) -> None:
    """A ground station joining late fetches what a vehicle already mapped; the
    vehicle's service restarts (new boot, new reset counter, key-frame ids from
    0 again): still one vehicle, its earlier map kept aside, the new one exact."""
    ep = endpoint()
    vcfg = ZenohConfig(vehicle="v1", mode="client", connect=(ep,), status_period_s=0.2)
    with router(RouterConfig(listen=(ep,))):
        first = ZenohOutput(vcfg)
        assert first.wait_connected(WAIT_S)
        fly(first, 5, [0, 1], seed=1)
        with ground(ZenohConfig(connect=(ep,))) as station:  # joins after the key frames
            first_crcs = {int(k): v for k, v in first.run_stats()["keyframe_crc32"].items()}
            pump(station, lambda: "v1" in station.vehicles
                 and station.vehicles["v1"].crcs == first_crcs, "late join: the map fetched")
            first.close()

            second = ZenohOutput(vcfg)
            assert second.wait_connected(WAIT_S) and second.boot != first.boot
            fly(second, 5, [0, 1, 2], seed=2, reset_counter=3)
            crcs = {int(k): v for k, v in second.run_stats()["keyframe_crc32"].items()}
            second.close()
            v = station.vehicles["v1"]
            pump(station, lambda: v.crcs == crcs and v.boot == second.boot
                 and v.last_status.get("map_digest") == map_digest(crcs), "the new boot's map")
            assert list(station.vehicles) == ["v1"]
            assert v.restarts == 1 and len(v.earlier) == 1
            assert {k: v.earlier[0].keyframes[k].num_points for k in (0, 1)} and \
                set(v.earlier[0].keyframes) == {0, 1}
            assert v.digest() == map_digest(crcs) and set(crcs) == {0, 1, 2}
            files = write_fleet(tmp_path, station.summary(), station.vehicles)
    fleet = json.loads((tmp_path / "fleet.json").read_text())
    assert list(fleet["vehicles"]) == ["v1"]
    got = fleet["vehicles"]["v1"]
    assert got["keyframes"] == 3 and got["restarts"] == 1 and got["poses"] >= 1
    assert got["keyframe_crc32"] == {str(k): c for k, c in crcs.items()}
    assert {p.name for p in files} >= {"fleet.json", "v1.ply", "v1.boot1.ply", "fleet.png"}


def test_key_frames_made_while_the_router_is_down_reach_the_ground_after() -> None:
    """The router goes away, the vehicle makes two key frames (its puts find
    no route), the router comes back on the same endpoint: both sessions
    reconnect by themselves, the status digest differs from the ground's, and
    the ground fetches the map: every key frame, content checked."""
    ep = endpoint()
    vcfg = ZenohConfig(vehicle="o1", mode="client", connect=(ep,), status_period_s=0.2)
    r1 = open_session(router_config(RouterConfig(listen=(ep,))))
    with ground(ZenohConfig(connect=(ep,))) as station, ZenohOutput(vcfg) as out:
        assert out.wait_connected(WAIT_S)
        fly(out, 3, [0], seed=7)
        pump(station, lambda: len(station.vehicles.get("o1", _NoKeys()).keyframes) == 1,
             "the first key frame")
        v = station.vehicles["o1"]
        fetches = v.fetches
        r1.close()
        fly(out, 3, [0, 1, 2], seed=8)  # key frame 0 refined (new content), 1 and 2 new
        crcs = {int(k): c for k, c in out.run_stats()["keyframe_crc32"].items()}
        with router(RouterConfig(listen=(ep,))):
            pump(station, lambda: v.crcs == crcs, "the map after the router came back")
        assert v.fetches > fetches and list(station.vehicles) == ["o1"] and v.restarts == 0


def test_the_fleet_status_queryable_answers_for_other_tools() -> None:
    ep = endpoint()
    with router(RouterConfig(listen=(ep,))), ground(ZenohConfig(connect=(ep,))) as station:
        with ZenohOutput(ZenohConfig(vehicle="q1", mode="client", connect=(ep,))) as out:
            assert out.wait_connected(WAIT_S)
            fly(out, 3, [0], seed=3)
            pump(station, lambda: len(station.vehicles.get("q1", _NoKeys()).keyframes) == 1,
                 "key frame")
        station.refresh_snapshot()
        with open_session(session_config(ZenohConfig(connect=(ep,)), mode="client")) as tool:
            replies = list(tool.get("nislam/@fleet/status", timeout=10.0))
    assert len(replies) == 1 and replies[0].ok is not None
    fleet = json.loads(replies[0].ok.payload.to_bytes())
    assert fleet["vehicles"]["q1"]["keyframes"] == 1


class _NoKeys:
    keyframes: dict = {}


def test_map_rate_limit_spreads_key_frames_over_time() -> None:
    lim = RateLimit(1000.0)  # 1 kB/s, a one-second allowance
    assert lim.delay_s(1000, now=0.0) == 0.0  # the allowance
    assert lim.delay_s(500, now=0.0) == pytest.approx(0.5)
    assert lim.delay_s(500, now=0.5) == pytest.approx(0.5)  # queued behind the last
    assert lim.delay_s(2000, now=10.0) == pytest.approx(1.0)  # after a quiet spell
    assert RateLimit(0.0).delay_s(10**9, now=0.0) == 0.0  # no limit


# --------------------------------------------------------------------------- security


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[str, str]]:
    folder = tmp_path_factory.mktemp("pki")
    make_ca(folder, "ca")
    certs = {cn: make_cert(folder, cn, "ca") for cn in ("router", "v1", "v2", "ground")}
    stranger = folder / "stranger"  # a stranger's CA, and a "v1" certificate from it
    make_ca(stranger, "ca")
    certs["rogue-v1"] = make_cert(stranger, "v1", "ca")
    certs["ca"] = (str(folder / "ca.pem"), "")
    return certs


def _tls(pki: dict[str, tuple[str, str]], cn: str, ca: str = "ca") -> dict[str, str]:
    cert, key = pki[cn]
    return {"tls_root_ca": pki[ca][0], "tls_certificate": cert, "tls_private_key": key}


def _open_briefly(conf: zenoh.Config) -> zenoh.Session:
    """Open giving up after 3 s (a client otherwise waits for its router)."""
    conf.insert_json5("connect/timeout_ms", "3000")
    return zenoh.open(conf)


def test_tls_and_acl_only_the_fleet_connects_each_vehicle_under_its_own_key(
        pki: dict[str, tuple[str, str]]) -> None:
    ep = endpoint("tls")
    rcfg = RouterConfig(listen=(ep,), acl=True, vehicles=("v1", "v2"), grounds=("ground",),
                        **_tls(pki, "router"))
    with router(rcfg), ground(ZenohConfig(connect=(ep,), **_tls(pki, "ground"))) as station:
        vehicles = [ZenohOutput(ZenohConfig(vehicle=v, mode="client", connect=(ep,),
                                            **_tls(pki, v))) for v in ("v1", "v2")]
        try:
            v1, v2 = vehicles
            for i, v in enumerate(vehicles):
                assert v.wait_connected(WAIT_S)
                fly(v, 3, [0], seed=4 + i)
            pump(station, lambda: len(station.vehicles) == 2 and all(
                len(station.vehicles[v].keyframes) == 1 and station.vehicles[v].poses == 3
                for v in ("v1", "v2")), "both vehicles' poses and key frames through the router")
            # v1 forges a pose of v2, then puts one of its own at the same
            # priority: once the ground has the second, the first was refused.
            before = {v: station.vehicles[v].poses for v in ("v1", "v2")}
            v1.session.put("nislam/v2/pose", json.dumps({"trusted": False, "t_s": 0.0}))
            v1.session.put("nislam/v1/pose", json.dumps({"trusted": False, "t_s": 9.0}))
            pump(station, lambda: station.vehicles["v1"].poses > before["v1"], "v1's own pose")
            assert station.vehicles["v2"].poses == before["v2"], "v1 published as v2"
            # Only the ground queries every map: v1 gets nothing of v2's.
            assert [r for r in v1.session.get("nislam/v2/map/**", timeout=3.0) if r.ok] == []
            got = [r for r in station.session.get("nislam/v2/map/**", timeout=10.0) if r.ok]
            assert len(got) == 1
        finally:
            for v in vehicles:
                v.close()
        # Strangers: no certificate, another CA's "v1", plain TCP.
        no_cert = session_config(ZenohConfig(connect=(ep,), tls_root_ca=pki["ca"][0],
                                             tls_certificate=pki["v2"][0],
                                             tls_private_key=pki["v2"][1]), mode="client")
        no_cert.insert_json5("transport/link/tls/enable_mtls", "true")
        no_cert.insert_json5("transport/link/tls/connect_certificate", "null")
        no_cert.insert_json5("transport/link/tls/connect_private_key", "null")
        rogue = session_config(ZenohConfig(connect=(ep,), **_tls(pki, "rogue-v1")),
                               mode="client")
        plain = session_config(ZenohConfig(connect=("tcp" + ep[3:],)), mode="client")
        for name, conf in (("no certificate", no_cert), ("a stranger's CA", rogue),
                           ("plain TCP", plain)):
            with pytest.raises(zenoh.ZError):
                _open_briefly(conf).close()
                pytest.fail(f"a client with {name} connected")
        ok = _open_briefly(session_config(ZenohConfig(connect=(ep,), **_tls(pki, "v2")),
                                          mode="client"))
        ok.close()  # the same open with a fleet certificate works


def test_router_configuration_is_checked_and_exported_for_zenohd(
        pki: dict[str, tuple[str, str]]) -> None:
    with pytest.raises(NislamError, match="acl = true needs TLS"):
        router_config(RouterConfig(acl=True, vehicles=("v1",)))
    with pytest.raises(NislamError, match="tls/HOST:PORT"):
        router_config(RouterConfig(listen=("tcp/127.0.0.1:7447",), **_tls(pki, "router")))
    with pytest.raises(NislamError, match="tls_private_key"):
        session_config(ZenohConfig(tls_root_ca=pki["ca"][0], tls_certificate=pki["v1"][0]))
    cfg = RouterConfig(listen=("tls/127.0.0.1:7447",), acl=True, vehicles=("v1",),
                       **_tls(pki, "router"))
    exported = json.loads(router_json(cfg))
    assert exported["mode"] == "router" and exported["access_control"]["enabled"]
    assert exported["transport"]["link"]["tls"]["enable_mtls"] is True
    zenoh.Config.from_json5(router_json(cfg))  # what zenohd -c reads
    acl = access_control(cfg)
    v1_rules = [r for r in acl["rules"] if r["id"].startswith("v1-")]
    assert all(r["key_exprs"] == ["nislam/v1/**"] for r in v1_rules)
    assert not any("query" in r["messages"] for r in v1_rules if r["flows"] == ["ingress"])


class _Recorder:
    """The parts of a zenoh.Session ZenohOutput uses, recording the QoS asked for."""

    def __init__(self) -> None:
        self.publishers: dict[str, dict] = {}
        self.puts: list[tuple[str, dict]] = []

    def declare_publisher(self, key: str, **kwargs) -> _Recorder:
        self.publishers[key] = kwargs
        return self

    def put(self, key: str, payload=None, **kwargs) -> None:
        if payload is not None:  # a session put (key frames); a publisher's put has no key
            self.puts.append((key, kwargs))

    def declare_matching_listener(self, callback) -> _Recorder:
        return self

    def declare_queryable(self, key: str, callback) -> _Recorder:
        return self

    def liveliness(self) -> _Recorder:
        return self

    def declare_token(self, key: str) -> _Recorder:
        return self

    def undeclare(self) -> None:
        pass


def test_poses_go_at_a_higher_priority_than_key_frames() -> None:
    rec = _Recorder()
    with ZenohOutput(ZenohConfig(vehicle="p1"), session=rec) as out:
        out.publish(track_result(0.0, finished=(keyframe(0, shape=(10, 10)),)))
        wait_until(lambda: rec.puts, "key frame put")
    pose = rec.publishers["nislam/p1/pose"]["priority"]
    status = rec.publishers["nislam/p1/status"]["priority"]
    (key, kf), = rec.puts
    assert key == "nislam/p1/map/keyframe/0"
    # zenoh.Priority as an int: smaller is more urgent (REAL_TIME = 1).
    assert int(pose) < int(status) < int(kf["priority"])
    assert (pose, kf["priority"]) == (zenoh.Priority.INTERACTIVE_HIGH, zenoh.Priority.DATA_LOW)


class _NoSession:
    """Just enough of a zenoh session for a GroundStation fed by hand: every
    map query answers nothing (the vehicle's key frames are out of reach)."""

    class _Entity:
        def undeclare(self) -> None:
            pass

    def declare_subscriber(self, *_a, **_kw) -> _Entity:
        return self._Entity()

    declare_queryable = declare_subscriber

    def liveliness(self) -> _NoSession:
        return self

    def get(self, *_a, **_kw) -> list:
        return []


def test_a_map_behind_the_last_status_is_fetched_again_without_another_status() -> None:
    """The vehicle's last status (say, just before it lands) names a key
    frame the ground lacks, but came within REFETCH_S of the last fetch: the
    station fetches again once REFETCH_S has passed, with no further status.
    Before, it waited for a status that never came and kept 8 of 9 key frames
    (test_fleet's router restart under load)."""
    from onboard.outputs.ground import REFETCH_S

    now = [100.0]
    station = GroundStation(_NoSession(), clock=lambda: now[0])  # type: ignore[arg-type]
    try:
        station.events.put(("status", "v1", {"map_digest": map_digest({0: 1})}, 10, None))
        pump(station, lambda: "v1" in station.vehicles and station.vehicles["v1"].fetches == 1
             and not station.vehicles["v1"].fetching, "the discovery fetch done")
        v = station.vehicles["v1"]
        assert v.last_status and v.digest() != v.last_status["map_digest"]
        now[0] += 0.5 * REFETCH_S
        station.step(0.01)
        assert v.fetches == 1  # not sooner than REFETCH_S after the last
        now[0] += REFETCH_S
        station.step(0.01)
        assert v.fetches == 2
    finally:
        station.close()
