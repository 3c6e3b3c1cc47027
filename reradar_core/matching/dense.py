"""Dense registration of two radar images: the pose where sparse landmarks have nothing to hold on to.

Where nothing persistent stands near the road (open moor, a loch shore: simulator v11's open land on
``offroad-sim-hard``), a Navtech scan holds 3-20 Cen 2018 landmarks over its whole range and few of them repeat
between two drives, so landmark verification refuses the answer even when the far view's descriptor has named the
right place (docs/MODEL.md, "The far view"). The returns between the landmarks - low ridges, fence lines, the loch
shore 100-160 m away - still match as a whole. This module registers two scans by the normalised cross-correlation
of their whole Cartesian images: every heading on a coarse grid (``DenseConfig.coarse_step_deg``) at half
resolution, every translation within ``max_shift_m`` at once (FFT), then the best heading refined at full
resolution with sub-pixel peaks. It is ReRadar's own addition, not the paper's method (paper: Cen 2018 landmarks and
RANSAC, Sec. "Pose Estimation"); ``localization.far_view`` uses it only for queries that both views refused.

Two cues tell a registration that found the place from one that found noise: the peak's normalised correlation
(``DenseRegistration.score``) and how far it stands above the best peak at any heading more than
``DenseConfig.rival_heading_deg`` away (``heading_margin``: a scene that aligns only one way has a large margin; an
empty one aligns about as well at every heading). The decision threshold is ``localization.far_view``'s.

Images (``dense_image``): the scan's power minus each range bin's median over the azimuths (the receiver's
range-dependent floor and the ground clutter's level are not structure), resampled to the Cartesian grid,
smoothed (``blur_px``), high-passed (minus a ``highpass_px`` Gaussian: the slowly varying clutter level), made
zero-mean within the sensor disc and zero outside it. Frames: ``T_keyframe_query`` is the query's pose in the
keyframe's sensor frame (x forward, y left, metres; yaw radians), as ``CandidateVerification.T_keyframe_query``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from functools import lru_cache

import cv2
import numpy as np
from scipy import fft as sp_fft

from reradar_core.errors import ConfigError
from reradar_core.geometry.cartesian import CartesianConfig, pixel_to_metric, polar_to_cartesian
from reradar_core.io.scan import RadarScan, require_scan
from reradar_core.matching.ransac import fit_rigid_2d

__all__ = ["DenseConfig", "DenseRegistration", "dense_image", "dense_image_settings", "register_dense",
           "register_dense_best"]

#: Version of ``dense_image``'s recipe, part of ``dense_image_settings`` (a map stores the images it was built with).
DENSE_IMAGE_VERSION = 1


@dataclass(frozen=True)
class DenseConfig:
    """Settings of ``dense_image`` and ``register_dense`` (chosen on calibration routes of the
    ``offroad-sim-hard`` definition, world and route seeds 23-26, never on a benchmark drive; docs/MODEL.md,
    "Dense registration").

    Attributes:
        blur_px: Gaussian smoothing of the Cartesian image, pixels (default 1.0: speckle).
        highpass_px: the Gaussian whose blur is subtracted, pixels (default 4.0: ~5 m at the far view's 1.28 m/px,
            longer than a bank or fence return is wide, shorter than the clutter level varies).
        max_shift_m: largest translation searched, metres (default 30: beyond the benchmarks' 20-25 m radius).
        coarse_step_deg: heading grid of the half-resolution search, degrees (default 3.0).
        fine_step_deg, fine_span_deg: the full-resolution refinement around the coarse heading, degrees
            (default 0.5 steps over +-3).
        rival_heading_deg: a rival peak is one at a heading more than this from the best, degrees (default 10,
            the success threshold's heading).
        rival_shift_m: a rival translation is one more than this from the best at the best heading, metres
            (default 6: beyond the main peak's own width, ~2-3 px at 1.28 m/px, and within a short period of a
            regular row of posts or a straight bank, which it exists to catch).
    """

    blur_px: float = 1.0
    highpass_px: float = 4.0
    max_shift_m: float = 30.0
    coarse_step_deg: float = 3.0
    fine_step_deg: float = 0.5
    fine_span_deg: float = 3.0
    rival_heading_deg: float = 10.0
    rival_shift_m: float = 6.0

    def __post_init__(self) -> None:
        for name in ("blur_px", "highpass_px", "max_shift_m", "coarse_step_deg", "fine_step_deg",
                     "rival_heading_deg", "rival_shift_m"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ConfigError(f"dense registration {name} must be a positive number, got {v!r}")
        if not (math.isfinite(self.fine_span_deg) and self.fine_span_deg >= 0):
            raise ConfigError(f"dense registration fine_span_deg must be >= 0, got {self.fine_span_deg!r}")
        if self.coarse_step_deg > 30 or self.rival_heading_deg >= 180:
            raise ConfigError("dense registration needs coarse_step_deg <= 30 and rival_heading_deg < 180")
        # each bounds the work of one search: FFT size grows with the shift, rotations with span / step
        if self.max_shift_m > 200 or self.fine_span_deg > 30 or self.fine_step_deg < 0.05 \
                or self.coarse_step_deg < 0.5 or self.blur_px > 50 or self.highpass_px > 50:
            raise ConfigError("dense registration needs max_shift_m <= 200, fine_span_deg <= 30, fine_step_deg >= "
                              "0.05, coarse_step_deg >= 0.5 and blur_px, highpass_px <= 50")


@dataclass(frozen=True)
class DenseRegistration:
    """The best alignment of a query image onto a keyframe image.

    Attributes:
        T_keyframe_query: (3,) float64 (x m, y m, yaw rad), the query's pose in the keyframe's sensor frame.
        score: normalised cross-correlation at the best coarse (half-resolution) peak, in [-1, 1].
        heading_margin: ``score`` minus the best coarse peak at headings more than ``rival_heading_deg`` away.
        fine_score: normalised cross-correlation of the refined full-resolution peak.
        shift_margin: 1 - (the best full-resolution peak at the same heading farther than ``rival_shift_m`` from
            the answer's) / ``fine_score``: how uniquely the translation is fixed, relative to the peak (near 0 where
            the scene aligns as well one step along itself: a straight bank, a regular row of posts; 0.53-0.90 for
            the right answers on the calibration routes, docs/MODEL.md "Dense registration").
        at_edge: the peak lies on the border of the +-``max_shift_m`` window: the true shift may lie beyond it.
    """

    T_keyframe_query: np.ndarray
    score: float
    heading_margin: float
    fine_score: float
    shift_margin: float = 0.0
    at_edge: bool = False


def dense_image_settings(config: DenseConfig) -> str:
    """Canonical JSON of what ``dense_image`` depends on (recipe version, ``blur_px``, ``highpass_px``): a map
    stores it with its keyframes' dense images, and a reader whose settings differ does not correlate with them."""
    return json.dumps({"version": DENSE_IMAGE_VERSION, "blur_px": float(config.blur_px),
                       "highpass_px": float(config.highpass_px)}, sort_keys=True)


@lru_cache(maxsize=8)
def _disc(width_px: int) -> np.ndarray:
    c = (width_px - 1) / 2.0
    yy, xx = np.mgrid[:width_px, :width_px]
    disc = np.hypot(yy - c, xx - c) <= c
    disc.setflags(write=False)
    return disc


def dense_image(scan: RadarScan, cartesian: CartesianConfig, config: DenseConfig = DenseConfig()) -> np.ndarray:
    """The image ``register_dense`` correlates (module docstring).

    Args:
        scan: a ``RadarScan`` (power (A, R) float32 in [0, 1]).
        cartesian: the image geometry (the far view's: 257 px at 1.28 m/px).

    Returns:
        (W, W) float32, zero-mean within the sensor disc, 0 outside; W = ``cartesian.width_px``.
    """
    require_scan(scan, "dense_image")
    power = scan.power
    floor = np.median(power, axis=0, keepdims=True)
    img = polar_to_cartesian(replace(scan, power=np.maximum(power - floor, 0.0).astype(np.float32)), cartesian)
    img = cv2.GaussianBlur(img, (0, 0), config.blur_px)
    img = img - cv2.GaussianBlur(img, (0, 0), config.highpass_px)
    disc = _disc(cartesian.width_px)
    return np.where(disc, img - img[disc].mean(), 0.0).astype(np.float32)


def _rotated(img: np.ndarray, angles_deg: np.ndarray) -> np.ndarray:
    """(n, W, W) copies of ``img`` rotated about its centre pixel by each angle (cv2: counter-clockwise on screen)."""
    n = img.shape[0]
    c = (n - 1) / 2.0
    return np.stack([cv2.warpAffine(img, cv2.getRotationMatrix2D((c, c), float(a), 1.0), (n, n),
                                    flags=cv2.INTER_LINEAR) for a in angles_deg])


@dataclass(frozen=True)
class _QuerySpectra:
    """A stack of query images (e.g. rotated copies) transformed once, to correlate with several keyframes."""

    conj_fft: np.ndarray  # (n, size, size // 2 + 1) complex: conjugated zero-padded spectra
    norms: np.ndarray  # (n,) L2 norms of the images
    size: int  # FFT side: image side + largest shift, so no shift wraps round
    shift_px: int  # largest shift searched, pixels


def _query_spectra(queries: np.ndarray, shift_px: int) -> _QuerySpectra:
    size = sp_fft.next_fast_len(queries.shape[1] + shift_px, real=True)
    return _QuerySpectra(np.conj(sp_fft.rfft2(queries, s=(size, size), axes=(-2, -1))),
                         np.linalg.norm(queries.reshape(len(queries), -1), axis=1), size, shift_px)


def _correlate(keyframe: np.ndarray, queries: _QuerySpectra) -> np.ndarray:
    """(n, 2S+1, 2S+1) normalised cross-correlation: [k, S+dr, S+dc] compares query k moved by (dr, dc) pixels
    (rows, cols) with the keyframe image, S = ``queries.shift_px``."""
    size, s = queries.size, queries.shift_px
    cc = sp_fft.irfft2(sp_fft.rfft2(keyframe, s=(size, size))[None] * queries.conj_fft, s=(size, size), axes=(-2, -1))
    cc = np.roll(cc, (s, s), axis=(-2, -1))[:, :2 * s + 1, :2 * s + 1]
    norms = float(np.linalg.norm(keyframe)) * queries.norms
    return cc / np.maximum(norms, 1e-12)[:, None, None]


def _vertex(lo: float, mid: float, hi: float) -> float:
    """Sub-sample offset of a parabola's peak through three equally spaced samples (0 when not a peak)."""
    d = lo - 2.0 * mid + hi
    return 0.0 if d >= 0 else float(np.clip(0.5 * (lo - hi) / d, -0.5, 0.5))


def _pose_from_pixels(angle_deg: float, shift_rc: tuple[float, float], cartesian: CartesianConfig) -> np.ndarray:
    """T_keyframe_query from an image rotation (cv2 degrees) and shift (rows, cols): the query pixel p lands on
    keyframe pixel R p + shift; three pixels mapped to metres fix the rigid motion exactly."""
    c = cartesian.centre_px
    m = cv2.getRotationMatrix2D((c, c), angle_deg, 1.0)
    cols_rows = np.array([[c - 40.0, c - 40.0], [c + 40.0, c - 40.0], [c, c + 40.0], [c, c]])
    moved = cols_rows @ m[:, :2].T + m[:, 2] + np.array([shift_rc[1], shift_rc[0]])
    return fit_rigid_2d(pixel_to_metric(cols_rows[:, ::-1], cartesian), pixel_to_metric(moved[:, ::-1], cartesian))


def register_dense(query: np.ndarray, keyframe: np.ndarray, cartesian: CartesianConfig,
                   config: DenseConfig = DenseConfig()) -> DenseRegistration:
    """Register ``query`` onto ``keyframe`` (both ``dense_image`` outputs of one geometry; module docstring).

    Args:
        query, keyframe: (W, W) float images, W = ``cartesian.width_px``.
        cartesian: their geometry (metres per pixel for the shift's units).

    Returns:
        ``DenseRegistration``: the pose, the coarse peak's score and its margin over rival headings.

    Raises:
        ValueError: the images are not both (W, W) with W = ``cartesian.width_px``, or not finite.
    """
    return register_dense_best(query, [keyframe], cartesian, config)[1]


def _image(img: np.ndarray, width_px: int, what: str) -> np.ndarray:
    a = np.asarray(img, dtype=np.float32)
    if a.shape != (width_px, width_px):
        raise ValueError(f"dense registration needs ({width_px}, {width_px}) images, got {a.shape} for {what}")
    if not np.isfinite(a).all():
        raise ValueError(f"dense registration: the {what} image contains NaN or infinite values")
    return a


def register_dense_best(query: np.ndarray, keyframes: list[np.ndarray], cartesian: CartesianConfig,
                        config: DenseConfig = DenseConfig()) -> tuple[int, DenseRegistration]:
    """Register ``query`` onto each keyframe image at the coarse stage and refine the best one.

    The query's rotated half-resolution copies are made and transformed once for all keyframes; only the
    winner (highest coarse ``score``) is refined at full resolution, so k candidates cost k coarse searches and
    one refinement (``register_dense`` is the one-keyframe case).

    Args:
        query: (W, W) float ``dense_image``; keyframes: one or more (W, W) float ``dense_image`` of the same
            geometry; cartesian: that geometry.

    Returns:
        (index of the best keyframe in ``keyframes``, its ``DenseRegistration``).

    Raises:
        ValueError: no keyframe, an image of another shape, or non-finite values.
    """
    w = cartesian.width_px
    q = _image(query, w, "query")
    kfs = [_image(k, w, f"keyframe {i}") for i, k in enumerate(keyframes)]
    if not kfs:
        raise ValueError("dense registration needs at least one keyframe image")
    # coarse: every heading at half resolution, the query's rotations transformed once
    angles = np.arange(0.0, 360.0, config.coarse_step_deg)
    shift_half = max(1, int(math.ceil(config.max_shift_m / (2.0 * cartesian.resolution_m))))
    rotated = _query_spectra(_rotated(cv2.resize(q, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA), angles),
                             shift_half)
    coarse: list[tuple[float, float, float]] = []
    for k in kfs:
        k_half = cv2.resize(k, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
        per_angle = _correlate(k_half, rotated).reshape(len(angles), -1).max(axis=1)
        best = int(np.argmax(per_angle))
        apart = np.abs((angles - angles[best] + 180.0) % 360.0 - 180.0) > config.rival_heading_deg
        rival = float(per_angle[apart].max()) if apart.any() else -1.0
        coarse.append((float(per_angle[best]), float(angles[best]), float(per_angle[best] - rival)))
    win = int(np.argmax([c[0] for c in coarse]))
    score, heading, margin = coarse[win]
    # fine: full resolution around the winner's coarse heading, sub-pixel and sub-step peaks
    fine = heading + np.arange(-config.fine_span_deg, config.fine_span_deg + 1e-9, config.fine_step_deg)
    shift = max(1, int(math.ceil(config.max_shift_m / cartesian.resolution_m)))
    cc = _correlate(kfs[win], _query_spectra(_rotated(q, fine), shift))
    ai, r, c = np.unravel_index(int(np.argmax(cc)), cc.shape)
    dr = _vertex(cc[ai, r - 1, c], cc[ai, r, c], cc[ai, r + 1, c]) if 0 < r < 2 * shift else 0.0
    dc = _vertex(cc[ai, r, c - 1], cc[ai, r, c], cc[ai, r, c + 1]) if 0 < c < 2 * shift else 0.0
    peaks = cc.reshape(len(fine), -1).max(axis=1)
    da = (_vertex(peaks[ai - 1], peaks[ai], peaks[ai + 1]) * config.fine_step_deg
          if 0 < ai < len(fine) - 1 else 0.0)
    T = _pose_from_pixels(float(fine[ai] + da), (r - shift + dr, c - shift + dc), cartesian)
    surface = cc[ai]
    rows, cols = np.ogrid[:surface.shape[0], :surface.shape[1]]
    apart_px = config.rival_shift_m / cartesian.resolution_m
    rival_shift = surface[(rows - r) ** 2 + (cols - c) ** 2 > apart_px ** 2]
    peak = float(surface[r, c])
    shift_margin = 1.0 - float(rival_shift.max()) / peak if rival_shift.size and peak > 0 else 0.0
    at_edge = bool(r in (0, 2 * shift) or c in (0, 2 * shift))
    return win, DenseRegistration(T, score, margin, float(cc[ai, r, c]), shift_margin, at_edge)
