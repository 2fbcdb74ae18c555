"""What the NI-SLAM diagnostic scripts (nislam_split.py, nislam_handover.py,
nislam_peak.py) share: the command line (a sequence, tracker settings as
KEY=VALUE, attitude noise) and the set-up it names."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from onboard.nislam.params import NislamParams  # noqa: E402
from sim_replay.attitude import AttitudeErrorModel, attitude_for_replay  # noqa: E402
from sim_replay.tum import Sequence, open_sequence  # noqa: E402


def parser(description: str) -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("seq", type=Path)
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="[nislam] settings, e.g. depth_cell_step=1")
    ap.add_argument("--noise-deg", type=float, default=0.0, help="white attitude noise added")
    ap.add_argument("--seed", type=int, default=1)
    return ap


def _value(text: str) -> bool | int | float:
    if text in ("true", "false"):
        return text == "true"
    return float(text) if any(c in text for c in ".e") else int(text)


def setup(args: argparse.Namespace) -> tuple[NislamParams, Sequence, Any]:
    """The tracker's settings, the sequence and its attitude source."""
    over = {k: _value(v) for k, v in (s.split("=", 1) for s in args.set)}
    params = dataclasses.replace(NislamParams(), **over)
    seq = open_sequence(args.seq)
    att, _ = attitude_for_replay(seq, AttitudeErrorModel(noise_deg=args.noise_deg, seed=args.seed))
    return params, seq, att


def rms_mm(x: np.ndarray) -> float:
    x = np.asarray(x)
    return float(np.sqrt(np.mean(x**2))) * 1e3 if x.size else float("nan")
