"""Work a frame's pose does not need, done after the pose went out.

Refining the key with the frame (Eq. 19) and making a new key (Eq. 17:
projection, the filter's FFTs, the map entry) serve the next frames only.
The tracker queues them during `track()`, and the caller runs them once it
has sent the pose (`finish_frame()`): the flight controller gets the pose
without waiting for them. Nothing else changes: each queued job runs before
anything reads what it writes (all of them at the start of the next frame,
a key's own before that key is matched or handed out again), so the poses
are the same as with the work done in place.
"""

from __future__ import annotations

from collections.abc import Callable


class Deferred:
    """Jobs in order, each tagged with the object it writes (None: the
    tracker's own state)."""

    def __init__(self) -> None:
        self._jobs: list[tuple[object | None, Callable[[], object]]] = []

    def __len__(self) -> int:
        return len(self._jobs)

    def add(self, target: object | None, job: Callable[[], object]) -> None:
        self._jobs.append((target, job))

    def run(self, target: object | None = None) -> None:
        """Every job (`target` None), or the jobs on `target` (by identity), in order."""
        if not self._jobs:
            return
        if target is None:
            jobs, self._jobs = self._jobs, []
        else:
            jobs = [j for j in self._jobs if j[0] is target]
            self._jobs = [j for j in self._jobs if j[0] is not target]
        for _, job in jobs:
            job()
