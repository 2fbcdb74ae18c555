"""Output folders of `nislam sim` and `nislam faults`: what is ours, and the
rule that a recording somebody else wrote is never cleared."""

from __future__ import annotations

import shutil
from pathlib import Path

from onboard import NislamError

SIM_MANIFEST = "sim.json"
FAULTS_MANIFEST = "faults.json"  # written by sim_replay.faults; also marks a folder as ours
# Written first, removed last: a render cut short (Ctrl-C during `make run`)
# leaves a folder that is still ours to clear, and that no reader takes for a
# whole recording.
PARTIAL_MARKER = ".nislam-partial"
OUR_FILES = ("rgb.txt", "depth.txt", "groundtruth.txt", "attitude.txt", "camera.toml",
             SIM_MANIFEST, FAULTS_MANIFEST)
OUR_DIRS = ("rgb", "depth")


def prepare_out_dir(out_dir: Path) -> None:
    """Make `out_dir` ready for a recording: create it, or clear the files of
    an earlier one of ours. A folder holding a recording we did not write (a
    real one!) is refused; unrelated files and folders are left alone."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise NislamError(f"{out_dir} exists and is not a folder")
    if out_dir.is_dir():
        ours = any((out_dir / n).is_file() for n in (SIM_MANIFEST, FAULTS_MANIFEST,
                                                       PARTIAL_MARKER))
        foreign = [n for n in (*OUR_FILES, *OUR_DIRS) if (out_dir / n).exists()]
        if foreign and not ours:
            raise NislamError(
                f"{out_dir} already holds a recording ({foreign[0]}) not written by nislam "
                f"sim/faults; choose another --out"
            )
        for n in OUR_FILES:
            (out_dir / n).unlink(missing_ok=True)
        for d in OUR_DIRS:
            shutil.rmtree(out_dir / d, ignore_errors=True)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / PARTIAL_MARKER).write_text("a recording being written (nislam sim/faults)\n")
    except OSError as e:
        raise NislamError(f"cannot create output folder {out_dir}: {e.strerror}") from None


def finish_out_dir(out_dir: Path) -> None:
    """The recording in `out_dir` is complete (see PARTIAL_MARKER)."""
    (Path(out_dir) / PARTIAL_MARKER).unlink(missing_ok=True)


def check_complete(seq_dir: Path) -> None:
    """Refuse, in one line, a recording whose writing was cut short."""
    if (Path(seq_dir) / PARTIAL_MARKER).is_file():
        raise NislamError(f"{seq_dir} holds an unfinished recording (its writing was "
                          f"interrupted); write it again")
