"""NI-SLAM key frames: the learned filter, refined images and pose of a key, and
the memory every key lives in, allocated once.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from onboard.nislam import kernels as kern
from onboard.nislam.calibration import RotationResidual, overlap
from onboard.nislam.correlation import KernelCorrelationFilter
from onboard.nislam.projection import AxonometricImage


@dataclass
class KeySlot:
    """The memory of one key frame: its projection, the images Eq. 18 compares
    frames with, the refined images and the filter's spectra (8 MB at
    480 x 360), allocated once by `KeyStore`."""

    gray: np.ndarray
    depth_m: np.ndarray
    mask: np.ndarray
    bgr: np.ndarray
    gray_ref: np.ndarray
    depth_ref: np.ndarray
    count: np.ndarray
    gray_fine: np.ndarray  # the key frame at `key_depth_stride`, as projected (Eq. 18)
    depth_fine: np.ndarray
    mask_fine: np.ndarray
    spectra: tuple[np.ndarray, np.ndarray]  # z_hat, alpha_hat (CCS-packed, onboard.nislam.correlation)

    @classmethod
    def allocate(cls, shape: tuple[int, int]) -> "KeySlot":
        h, w = shape

        def resident(a: np.ndarray) -> np.ndarray:
            a.fill(0)  # written now, so the pages are resident from the start
            return a

        def grid() -> np.ndarray:
            return resident(np.empty(shape, np.float32))

        return cls(grid(), grid(), grid(), resident(np.empty((h, w, 3), np.uint8)), grid(),
                   grid(), grid(), grid(), grid(), grid(), (grid(), grid()))

    def hold(self, img: AxonometricImage, fine: AxonometricImage) -> AxonometricImage:
        """`img` copied into this slot, and `fine` (the key frame at
        `key_depth_stride`, or `img` itself): Eq. 18's images, the refined
        ones' start and the map's colour."""
        np.copyto(self.gray, img.gray)
        np.copyto(self.depth_m, img.depth_m)
        np.copyto(self.mask, img.mask)
        if fine.bgr is not None:
            np.copyto(self.bgr, fine.bgr)
        else:
            self.bgr.fill(0)  # not the colour of the slot's previous key
        np.copyto(self.gray_ref, fine.gray)
        np.copyto(self.depth_ref, fine.depth_m)
        np.copyto(self.count, fine.mask)
        np.copyto(self.gray_fine, fine.gray)
        np.copyto(self.depth_fine, fine.depth_m)
        np.copyto(self.mask_fine, fine.mask)
        return AxonometricImage(self.gray, self.depth_m, self.mask, img.res_m, self.bgr)


class KeyStore:
    """Memory for the key frames the tracker can hold at once (the kept keys
    and the one being made), allocated when the tracker is built. Key frames
    then never allocate: the process is at its working size from the first
    frame, so a long flight cannot creep towards the companion computer's
    memory limit, and a soak shows any real leak plainly."""

    def __init__(self, shape: tuple[int, int], slots: int) -> None:
        self._free = [KeySlot.allocate(shape) for _ in range(slots)]

    def take(self) -> KeySlot:
        if not self._free:
            raise RuntimeError("key store exhausted: a key frame was not given back")
        return self._free.pop()

    def give_back(self, slot: KeySlot) -> None:
        self._free.append(slot)


@dataclass
class Key:
    """Key frame state: the learned filter, the refined images and the pose.
    The arrays live in `slot` (see KeyStore)."""

    keyframe_id: int
    t_s: float
    p_W_m: np.ndarray
    R_W_C: np.ndarray
    img: AxonometricImage  # the key's projection, held in `slot`
    filt: KernelCorrelationFilter
    slot: KeySlot
    layers: "RotationResidual | None" = None
    shifts: list[tuple[float, float, float]] = field(default_factory=list)  # last two (t_s, du, dv)
    coverage: list[float] = field(default_factory=list)  # last two frames' share of the grid covered
    r_geom: np.ndarray | None = None  # the geometry's rotation from the attitude at t_s (Prev's)
    stride: int = 2  # pixel step of the cloud it was made from; its frames' clouds take the same
    # Eq. 18 against the key frame at `key_depth_stride` as projected (True), or
    # against the refined images (False: `key_depth_stride = 0`, the paper's)
    as_projected: bool = False

    @property
    def match_gray(self) -> np.ndarray:
        """The gray Eq. 18 gates a frame's cells against: with `as_projected`
        the key frame at `key_depth_stride` as projected, not the refined one
        (Eq. 19 carries each frame's depth in by that frame's own t_z, so a
        key refined from its frames follows their errors; docs/nislam-error-
        budget.md, "A key's depth from every pixel"); else the refined one."""
        return self.slot.gray_fine if self.as_projected else self.slot.gray_ref

    @property
    def match_depth(self) -> np.ndarray:
        """The depth Eq. 18 compares a frame's cells with (as match_gray)."""
        return self.slot.depth_fine if self.as_projected else self.slot.depth_ref

    @property
    def gray_ref(self) -> np.ndarray:
        """Refined gray (count-weighted mean, Eq. 19a): the map's."""
        return self.slot.gray_ref

    @property
    def depth_ref(self) -> np.ndarray:
        """Refined depth (Eq. 19b): the map's."""
        return self.slot.depth_ref

    @property
    def count(self) -> np.ndarray:
        """W_k of Eq. 19b."""
        return self.slot.count

    @property
    def mask0(self) -> np.ndarray:
        """Original key mask W_0 of match_depth."""
        return self.slot.mask_fine if self.as_projected else self.slot.mask

    def predicted_shift(self, t_s: float) -> tuple[float, float]:
        """Constant-velocity prediction of the shift at `t_s` against this key,
        in time rather than frames: after dropped frames it moves as far as
        the camera did."""
        if not self.shifts:
            return (0.0, 0.0)
        t1, u1, v1 = self.shifts[-1]
        if len(self.shifts) == 1:
            return (u1, v1)
        t0, u0, v0 = self.shifts[-2]
        k = (t_s - t1) / (t1 - t0) if t1 > t0 else 1.0
        return (u1 + k * (u1 - u0), v1 + k * (v1 - v0))

    def since_last_match_s(self, t_s: float) -> float:
        return t_s - (self.shifts[-1][0] if self.shifts else self.t_s)

    def leaving_grid(self, min_fraction: float) -> bool:
        """A turn carries the view off the key's grid: each frame covers less
        of it while the match stays firm (on `circle` PSR 35-55 down to the
        last frame), and the first frame below `min_fraction` fails the
        match. True when the next frame, extrapolated from the last two,
        would fall below it: the tracker hands the key over now, after this
        firm frame's pose, as Eq. 17 does, instead of on that failed match
        (then the pose waited for the kept keys, a new key made from the frame
        before and a second match)."""
        if len(self.coverage) < 2:
            return False
        before, now = self.coverage
        return 2.0 * now - before < min_fraction

    def refine(self, img: AxonometricImage, du: int, dv: int, tz: float,
               frac: tuple[float, float], subcell: bool, gate_m: float) -> None:
        """Count-weighted moving average of the key images (Eq. 19a/b), as an
        incremental mean: ref += (new - ref) * w_new / (W_k + w_new).
        `subcell`: the frame's depth carried to the sub-cell peak and gated as
        in Eq. 18 (kernels.refine_key)."""
        if subcell:
            kern.refine_key(self.gray_ref, self.depth_ref, self.count, img.gray,
                            img.depth_m, img.mask, du, dv, frac[0], frac[1], tz, gate_m)
            return
        ks, cs = overlap(self.gray_ref.shape, du, dv)
        w_new = img.mask[cs]
        cnt = self.count[ks]
        cnt += w_new
        gain = w_new / np.maximum(cnt, 1.0)
        self.gray_ref[ks] += (img.gray[cs] - self.gray_ref[ks]) * gain
        # Eq. 19 with I_new - dz: depth moved into the key's axes first.
        self.depth_ref[ks] += (img.depth_m[cs] + tz - self.depth_ref[ks]) * gain
