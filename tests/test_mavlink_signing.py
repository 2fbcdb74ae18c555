"""MAVLink 2 signing on the vision feed: the key file's rules, and a signing
peer in another process over UDP: with the same key its TIMESYNC requests are
answered and it accepts our signed ODOMETRY; unsigned or wrongly signed
requests are refused (never answered, counted)."""

from __future__ import annotations

import hashlib
import time
from pathlib import Path

import pytest
from fake_results import track_result
from subproc import REPO, JsonLinesProcess, free_port, python_script

from onboard import NislamError
from onboard.outputs.mavlink import MavlinkOutput
from onboard.outputs.mavlink_signing import load_signing_key
from onboard.outputs.settings import MavlinkConfig

PEER = REPO / "tests" / "peers" / "mavlink_signed_peer.py"
KEY_HEX = "8f" * 32
WAIT_S = 30.0


def key_file(tmp_path: Path, text: str, mode: int = 0o600) -> Path:
    p = tmp_path / "mavlink.key"
    p.write_text(text + "\n")
    p.chmod(mode)
    return p


def test_key_file_must_be_private_and_holds_hex_or_a_passphrase(tmp_path: Path) -> None:
    assert load_signing_key(key_file(tmp_path, KEY_HEX)) == bytes.fromhex(KEY_HEX)
    assert load_signing_key(key_file(tmp_path, "fleet secret")) == \
        hashlib.sha256(b"fleet secret").digest()  # MAVProxy's passphrase -> key
    for mode in (0o644, 0o640, 0o604):
        with pytest.raises(NislamError, match="chmod 600"):
            load_signing_key(key_file(tmp_path, KEY_HEX, mode))
    with pytest.raises(NislamError, match="empty"):
        load_signing_key(key_file(tmp_path, ""))
    with pytest.raises(NislamError, match="cannot read"):
        load_signing_key(tmp_path / "absent.key")


def run_feed(tmp_path: Path, peer_key: str | None) -> tuple[MavlinkOutput, JsonLinesProcess]:
    """Our signing feed sending to a peer; returns both, running."""
    port = free_port()
    peer = JsonLinesProcess(python_script(PEER, str(port),
                                          *(["--key", peer_key] if peer_key else [])))
    peer.wait_for(lambda ls: any(m.get("ready") for m in ls), WAIT_S, "peer ready")
    cfg = MavlinkConfig(enabled=True, connect=f"udpout:127.0.0.1:{port}",
                        signing_key_file=str(key_file(tmp_path, KEY_HEX)))
    return MavlinkOutput(cfg), peer


def feed_until(out: MavlinkOutput, pred, what: str) -> None:
    deadline = time.monotonic() + WAIT_S
    t = 0.0
    while not pred():
        assert time.monotonic() < deadline, f"{what}: not within {WAIT_S} s ({out.stats()})"
        out.publish(track_result(t, [t, 0.0, 0.0]))
        t += 0.02
        time.sleep(0.02)  # the feed's pace (50 Hz), not a synchronisation


def test_a_peer_with_the_key_is_answered_and_accepts_our_signed_poses(tmp_path: Path) -> None:
    out, peer = run_feed(tmp_path, KEY_HEX)
    try:
        feed_until(out, lambda: out.stats()["timesync_replies"] >= 3
                   and len(peer.of_type("ODOMETRY")) >= 3, "signed exchange")
        assert out.stats()["signature_rejects"] == 0
    finally:
        out.close()
        peer.stop()
    got = peer.of_type("ODOMETRY")
    assert got and all(m["signed"] for m in got)
    assert any(m.get("type") == "TIMESYNC" and m["tc1"] != 0 and m["signed"] for m in peer.lines)
    assert not [m for m in peer.lines if "refused" in m]


@pytest.mark.parametrize("peer_key", [None, "11" * 32], ids=["unsigned", "wrong key"])
def test_unsigned_or_wrongly_signed_requests_are_refused(tmp_path: Path,
                                                         peer_key: str | None) -> None:
    out, peer = run_feed(tmp_path, peer_key)
    try:
        feed_until(out, lambda: out.stats()["signature_rejects"] >= 10, "refused requests")
        assert out.stats()["timesync_replies"] == 0
    finally:
        out.close()
        peer.stop()
    # never answered (the TIMESYNC requests the feed sends itself carry tc1 = 0)
    assert not [m for m in peer.lines if m.get("type") == "TIMESYNC" and m["tc1"] != 0]
    if peer_key is not None:  # the peer with another key refuses ours in turn
        assert [m for m in peer.lines if "refused" in m]
        assert not peer.of_type("ODOMETRY")
