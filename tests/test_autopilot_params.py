"""The shipped autopilot parameter files hold what docs/autopilot-parameters.md
says they hold (and nothing the page does not explain)."""

from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def read_parm(path: Path) -> dict[str, float]:
    """ArduPilot .parm: `NAME VALUE`, `#` comments."""
    out: dict[str, float] = {}
    for line in path.read_text().splitlines():
        body = line.split("#", 1)[0].split()
        if body:
            assert len(body) == 2, line
            assert body[0] not in out, f"{body[0]} twice"
            out[body[0]] = float(body[1])
    return out


def read_px4(path: Path) -> dict[str, str]:
    """PX4 shell lines: `param set NAME VALUE`."""
    out: dict[str, str] = {}
    for line in path.read_text().splitlines():
        body = line.split("#", 1)[0].split()
        if body:
            assert body[:2] == ["param", "set"] and len(body) == 4, line
            out[body[2]] = body[3]
    return out


ARDUPILOT_EXTNAV = {
    "AHRS_EKF_TYPE": 3, "EK3_ENABLE": 1, "GPS1_TYPE": 0,
    "VISO_TYPE": 3, "VISO_POS_X": 0, "VISO_POS_Y": 0, "VISO_POS_Z": 0, "VISO_ORIENT": 0,
    "VISO_SCALE": 1, "VISO_DELAY_MS": 20, "VISO_QUAL_MIN": 0,
    "VISO_POS_M_NSE": 0.2, "VISO_YAW_M_NSE": 0.2, "VISO_VEL_M_NSE": 0.1,
    "EK3_SRC1_POSXY": 6, "EK3_SRC1_VELXY": 6, "EK3_SRC1_POSZ": 6, "EK3_SRC1_VELZ": 6,
    "EK3_SRC1_YAW": 6,
}


def test_ardupilot_files() -> None:
    extnav = read_parm(REPO / "config" / "ardupilot-extnav.parm")
    assert extnav == ARDUPILOT_EXTNAV
    baro = read_parm(REPO / "config" / "ardupilot-extnav-baro.parm")
    assert baro == {**ARDUPILOT_EXTNAV, "EK3_SRC1_POSZ": 1}  # only the height source differs


def test_px4_file() -> None:
    px4 = read_px4(REPO / "config" / "px4-ekf2-extnav.txt")
    assert px4 == {"EKF2_EV_CTRL": "15", "EKF2_HGT_REF": "3", "EKF2_GPS_CTRL": "0",
                   "EKF2_EV_DELAY": "0", "EKF2_EV_NOISE_MD": "0", "EKF2_EV_QMIN": "0",
                   "EKF2_EV_POS_X": "0", "EKF2_EV_POS_Y": "0", "EKF2_EV_POS_Z": "0"}
    # Integers, never "15.0": a bitmask must reach PX4 as an integer.
    assert all("." not in v for k, v in px4.items() if k != "EKF2_EV_DELAY")


def test_the_page_names_every_parameter_and_file() -> None:
    page = (REPO / "docs" / "autopilot-parameters.md").read_text()
    for name in ("ardupilot-extnav.parm", "ardupilot-extnav-baro.parm", "px4-ekf2-extnav.txt"):
        assert f"config/{name}" in page
    names = set(ARDUPILOT_EXTNAV) | set(read_px4(REPO / "config" / "px4-ekf2-extnav.txt"))
    for n in names:
        # VISO_POS_X/Y/Z and EKF2_EV_POS_X/Y/Z are written as one; EK3_SRC1_POSXY, `VELXY`, ...
        stem = n[:-2] if n[-2:] in ("_X", "_Y", "_Z") else n
        assert stem in page or n.removeprefix("EK3_SRC1_") in page, n
