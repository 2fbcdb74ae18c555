"""The files of `nislam run --out`, written so that a full disk or a kill
loses at most the last seconds, never the run.

`LiveTrajectory` appends every trusted pose to `trajectory.tum` as the run
goes (flushed every `flush_s`); at the end the service rewrites the file
whole (atomically) with the same poses. When a write fails (ENOSPC, EIO, a
vanished USB stick) the file is cut back to its last complete flush, one
warning line says what is kept, and the run goes on: the flight controller
still gets its poses. `FileWrites.attempt` does the same for the end-of-run
files: one line per file that could not be written, no traceback, no
`.tmp` left behind.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any

log = logging.getLogger(__name__)

TUM_HEADER = "# timestamp tx ty tz qx qy qz qw\n"


_open_file = open  # tests put a disk that fills up here


def _why(e: OSError) -> str:
    return e.strerror or str(e)


class LiveTrajectory:
    """trajectory.tum appended as the run goes; `open_fn` is for tests (an
    injected ENOSPC)."""

    def __init__(self, path: Path, flush_s: float = 1.0,
                 open_fn: Callable[..., IO[str]] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.path = Path(path)
        self.flush_s = flush_s
        self.open_fn = open_fn
        self.clock = clock
        self.failed: str | None = None  # why writing stopped
        self.poses_written = 0  # poses known to be on disk (flushed)
        self.last_t_s: float | None = None  # stamp of the last pose on disk
        self._f: IO[str] | None = None
        self._good_bytes = 0  # file size after the last complete flush
        self._lines: list[str] = []
        self._pending_t: float | None = None
        self._last_flush = clock()

    def open(self) -> None:
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._f = (self.open_fn or _open_file)(self.path, "w")
            self._lines.append(TUM_HEADER)
            self._flush()
        except OSError as e:
            self._fail(e)

    def append(self, t_s: float, p: Any, q: Any) -> None:
        if self._f is None:
            return
        self._lines.append(f"{t_s:.6f} {p[0]:.6f} {p[1]:.6f} {p[2]:.6f} "
                           f"{q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}\n")
        self._pending_t = t_s
        if self.clock() - self._last_flush >= self.flush_s:
            self._flush()

    def close(self) -> None:
        if self._f is None:
            return
        self._flush()
        f, self._f = self._f, None
        if f is not None:
            with contextlib.suppress(OSError):
                f.close()

    def _flush(self) -> None:
        self._last_flush = self.clock()
        if self._f is None or not self._lines:
            return
        n = sum(1 for ln in self._lines if not ln.startswith("#"))
        text = "".join(self._lines)
        try:
            self._f.write(text)
            self._f.flush()
        except OSError as e:
            self._fail(e)
            return
        self._lines = []
        self._good_bytes += len(text.encode())
        self.poses_written += n
        if n:
            self.last_t_s = self._pending_t

    def _fail(self, e: OSError) -> None:
        f, self._f = self._f, None
        self._lines = []
        if f is not None:
            # Cut a half-written line off: what stays is a readable TUM file.
            with contextlib.suppress(OSError, ValueError):
                os.ftruncate(f.fileno(), self._good_bytes)
            with contextlib.suppress(OSError, ValueError):
                f.close()
        upto = "no pose" if self.last_t_s is None else \
            f"{self.poses_written} poses, up to t={self.last_t_s:.3f} s"
        self.failed = f"cannot write {self.path}: {_why(e)}; it keeps {upto}"
        log.warning("%s; the run goes on", self.failed)


class FileWrites:
    """End-of-run writes that fail quietly one by one and are reported in
    one line at the end (see the module doc)."""

    def __init__(self) -> None:
        self.failed: list[str] = []  # file names not written
        self.why: str | None = None

    @contextlib.contextmanager
    def attempt(self, *paths: Path) -> Iterator[None]:
        """Run the block; on OSError note `paths` as not written, remove
        their `.tmp` files and go on."""
        try:
            yield
        except OSError as e:
            for p in paths:
                with contextlib.suppress(OSError):
                    p.with_name(p.name + ".tmp").unlink(missing_ok=True)
                self.failed.append(p.name)
            self.why = self.why or _why(e)
            log.debug("write failed", exc_info=True)

    def report(self, out_dir: Path, skip: tuple[str, ...] = ()) -> str | None:
        """One warning line naming what was not written (but `skip`: files
        whose failure was told already); None when all went well."""
        names = [n for n in dict.fromkeys(self.failed) if n not in skip]
        if not names:
            return None
        line = f"cannot write {', '.join(names)} in {out_dir}: {self.why}"
        log.warning("%s", line)
        return line
