"""Compile every numba kernel into numba's on-disk cache, so the first run
after an install does not (`python -m onboard.app.warm`, the last step of
`make venv`). A cold cache costs the first `nislam run` 10-30 s on a 2-core
machine before its first pose (`first_pose_s` counts it, docs/latency.md);
the service's own warm-up then only loads the cache. Under systemd the cache
is NUMBA_CACHE_DIR (systemd/nislam.service): run this with it set there."""

from __future__ import annotations

import time

from numba.core.dispatcher import Dispatcher

from onboard.core import attitude_smoothing
from onboard.fastorb import kernels as fastorb_kernels
from onboard.fastorb import refine_kernels
from onboard.nislam import filter_kernels
from onboard.nislam import kernels as nislam_kernels


WARMED = (nislam_kernels, attitude_smoothing, fastorb_kernels, refine_kernels)


def warm_up() -> None:
    for module in WARMED:
        module.warm_up()  # nislam_kernels' includes filter_kernels'


def compiled_signatures() -> dict[str, int]:
    """Each numba kernel's count of compiled (or cache-loaded) signatures in
    this process: a kernel called with argument types its warm_up() did not
    use compiles again on the pose's path (tests/test_warm.py)."""
    modules = (*WARMED, filter_kernels)
    return {f"{m.__name__}.{name}": len(obj.signatures) for m in modules
            for name, obj in vars(m).items() if isinstance(obj, Dispatcher)}


def main() -> None:
    t0 = time.perf_counter()
    warm_up()
    print(f"numba kernels compiled or loaded in {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
