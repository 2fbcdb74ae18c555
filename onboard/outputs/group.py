"""Where tracker results go: the `Output` protocol, a null object and a fan-out.

The tracking loop holds one `Output` and calls it on every frame without
asking which outputs are configured:

    with make_outputs(cfg.mavlink, cfg.zenoh) as out:
        for frame in frames:
            out.publish(tracker.track(frame, attitude))
        last = tracker.finish()
        if last is not None:
            out.publish_keyframe(last)

Contract of every output: `publish` and `publish_keyframe` return in well
under a millisecond and never raise for I/O problems (a slow or missing peer,
a link that went away): the work happens on the output's own threads behind
a bounded queue that drops the oldest entry. `close` stops those threads.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from types import TracebackType
from typing import TYPE_CHECKING, Any, Protocol

from onboard.core.messages import HealthReport, KeyframeCloud, TrackResult
from onboard.outputs.settings import MavlinkConfig, ZenohConfig

if TYPE_CHECKING:
    from onboard.outputs.mavlink import SharedLink

log = logging.getLogger(__name__)


class Output(Protocol):
    def publish(self, result: TrackResult) -> None:
        """Hand over one frame's result (its finished key frames included)."""
        ...

    def publish_keyframe(self, cloud: KeyframeCloud) -> None:
        """Hand over a key frame outside a result (`tracker.finish()`)."""
        ...

    def publish_health(self, report: HealthReport) -> None:
        """The onboard loop's health (each loop turn; `report.changed` on a change)."""
        ...

    def close(self) -> None:
        """Flush what is queued (briefly) and stop."""
        ...


class NullOutput:
    """Accepts everything and does nothing: the loop's output when none is
    configured (bench runs, tests)."""

    def publish(self, result: TrackResult) -> None:
        pass

    def publish_keyframe(self, cloud: KeyframeCloud) -> None:
        pass

    def publish_health(self, report: HealthReport) -> None:
        pass

    def close(self) -> None:
        pass

    def __enter__(self) -> NullOutput:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class OutputGroup:
    """Several outputs behind one: each call goes to every member in order."""

    def __init__(self, outputs: Sequence[Output]) -> None:
        self.outputs = tuple(outputs)

    def publish(self, result: TrackResult) -> None:
        for out in self.outputs:
            out.publish(result)

    def publish_keyframe(self, cloud: KeyframeCloud) -> None:
        for out in self.outputs:
            out.publish_keyframe(cloud)

    def publish_health(self, report: HealthReport) -> None:
        for out in self.outputs:
            out.publish_health(report)

    def stats(self) -> dict[str, dict[str, Any]]:
        """Each member's `run_stats()` or `stats()` (those that have one) by
        kind: "zenoh", "mavlink"."""
        out: dict[str, dict[str, Any]] = {}
        for o in self.outputs:
            fn = getattr(o, "run_stats", None) or getattr(o, "stats", None)
            if callable(fn):
                out[type(o).__name__.removesuffix("Output").lower()] = fn()
        return out

    def device_states(self) -> list[Any]:
        """The members' link states (onboard/core/device_state.py snapshots):
        the zenoh output's router, when it connects to one."""
        states = (getattr(o, "device_state", None) for o in self.outputs)
        return [s.snapshot() for s in states if s is not None]

    def close(self) -> None:
        """Close every member, even when one fails (the first error is raised)."""
        first: BaseException | None = None
        for out in self.outputs:
            try:
                out.close()
            except Exception as e:  # noqa: BLE001 - the others must still close
                log.error("closing %s failed: %s", type(out).__name__, e)
                first = first or e
        if first is not None:
            raise first

    def __enter__(self) -> OutputGroup:
        return self

    def __exit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def make_outputs(mavlink: MavlinkConfig, zenoh: ZenohConfig,
                 mavlink_link: SharedLink | None = None,
                 host_time_s: Callable[[float], float] | None = None) -> OutputGroup:
    """The outputs the sections enable ([mavlink] and [zenoh] `enabled`); an empty
    group (a null output) when none is. `mavlink_link`: the autopilot link
    when something else owns it (drivers.fc_link.FcLink); otherwise the
    MAVLink output opens [mavlink] connect itself. `host_time_s`: frame
    stamps -> host monotonic time, for sources that keep a recording's own
    stamps (the MAVLink feed's time_usec is always on the host's clock).
    pymavlink and zenoh load only when their output is enabled."""
    outputs: list[Output] = []
    try:
        if mavlink.enabled:
            from onboard.outputs.mavlink import MavlinkOutput

            outputs.append(MavlinkOutput(mavlink, link=mavlink_link, host_time_s=host_time_s))
        if zenoh.enabled:
            from onboard.outputs.zenoh_out import ZenohOutput

            outputs.append(ZenohOutput(zenoh))
    except BaseException:
        OutputGroup(outputs).close()
        raise
    return OutputGroup(outputs)
