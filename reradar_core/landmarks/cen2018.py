"""Cen 2018 radar landmark detector on polar Navtech scans.

S. H. Cen and P. Newman, "Precise ego-motion estimation with millimeter-wave radar under diverse and
challenging conditions", ICRA 2018, Sec. III-A; implemented as in the reference code
(keenan-burnett/yeti_radar_odometry, ``yeti_features/src/features.cpp``, ``cen2018features``).

Per azimuth (row) of the power s in [0, 1]:

1. q = s - mean_over_range(s)                          (remove the per-azimuth bias)
2. p = q convolved along range with a normalised Gaussian (sigma = 17 bins, kernel length 3 sigma = 51,
   centre at index 25, BORDER_REFLECT101)             (smoothed signal)
3. sigma_q = sqrt(sum_{q<0} 2 q^2 / count(q<0))      (noise scale from the negative half of q; 0.034 if none)
4. nqp = exp(-0.5 ((q - p) / sigma_q)^2), npp = exp(-0.5 (p / sigma_q)^2), b = nqp - npp
   y = q (1 - nqp) + p b                               (peak-preserving, noise-suppressing signal)
5. keep range bins j >= min_range with y > z_q sigma_q; one keypoint at the middle element (index len // 2)
   of each contiguous run of kept bins.

With numba (``reradar_core.jit``) the compiled detector runs (``cen2018_kernels``): p and y only where they
can decide, the same keypoints up to float32 rounding at the threshold, 2.0-2.3x faster. Without it (or with
``RERADAR_JIT=0``) everything is vectorised over the whole scan (one ``cv2.filter2D`` call for the Gaussian,
runs found with ``np.diff`` on the kept mask).
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import cv2
import numpy as np

from reradar_core.errors import ConfigError
from reradar_core.geometry.cartesian import polar_to_metric
from reradar_core.io.presets import get_preset
from reradar_core.io.scan import RadarScan, require_scan
from reradar_core.jit import jit_enabled
from reradar_core.landmarks.cen2018_kernels import certain_band, detect_rows

__all__ = ["Cen2018Config", "Landmarks", "detect_landmarks", "cen2018_response"]

logger = logging.getLogger(__name__)

#: sigma_q used by the reference code when an azimuth has no negative q values.
_SIGMA_Q_FALLBACK = 0.034


@dataclass(frozen=True)
class Cen2018Config:
    """Parameters of the Cen 2018 detector (defaults: the paper / reference code values).

    Attributes:
        z_q: detection threshold in units of the per-azimuth noise scale sigma_q (paper: 3.0).
        sigma_bins: standard deviation of the range smoothing Gaussian, bins (reference code: 17; odd).
            The kernel is ``3 * sigma_bins`` taps long.
        min_range_bins: bins closer than this are ignored (sensor leakage near the antenna). ``None`` takes
            the scan preset's ``landmark_min_range_bins`` (58 Oxford/OORD, 42 Boreas/MulRan, as in the
            reference code); 0 if the scan has no known preset.
        max_keypoints: optional cap; when set, keeps the strongest keypoints (largest y) first.
    """

    z_q: float = 3.0
    sigma_bins: int = 17
    min_range_bins: int | None = None
    max_keypoints: int | None = None

    def __post_init__(self) -> None:
        if not (np.isfinite(self.z_q) and self.z_q > 0):
            raise ConfigError(f"Cen2018Config.z_q must be a positive number, got {self.z_q}")
        if int(self.sigma_bins) != self.sigma_bins or self.sigma_bins < 1:
            raise ConfigError(f"Cen2018Config.sigma_bins must be a positive integer, got {self.sigma_bins}")
        if self.min_range_bins is not None and self.min_range_bins < 0:
            raise ConfigError(f"Cen2018Config.min_range_bins must be >= 0, got {self.min_range_bins}")
        if self.max_keypoints is not None and self.max_keypoints < 0:
            raise ConfigError(f"Cen2018Config.max_keypoints must be >= 0, got {self.max_keypoints}")


@dataclass
class Landmarks:
    """Keypoints detected on one polar scan, ordered by azimuth row then range bin (or by strength if capped).

    Attributes:
        azimuth_index: (N,) int64 row of the polar scan.
        range_bin: (N,) int64 column (range bin) of the polar scan.
        azimuth_rad: (N,) float64 azimuth, radians clockwise from sensor +x.
        range_m: (N,) float64 range of the bin centre, metres.
        xy_m: (N, 2) float64 position in the sensor frame (x forward, y left), metres.
        strength: (N,) float32 detector response y at the keypoint (power units, > z_q * sigma_q).
    """

    azimuth_index: np.ndarray
    range_bin: np.ndarray
    azimuth_rad: np.ndarray
    range_m: np.ndarray
    xy_m: np.ndarray
    strength: np.ndarray

    def __len__(self) -> int:
        return int(self.azimuth_index.shape[0])

    def subset(self, index: np.ndarray | slice) -> Landmarks:
        """The landmarks selected by ``index`` (boolean mask, integer array or slice)."""
        return Landmarks(
            self.azimuth_index[index],
            self.range_bin[index],
            self.azimuth_rad[index],
            self.range_m[index],
            self.xy_m[index],
            self.strength[index],
        )


def _gaussian_kernel(sigma_bins: int) -> np.ndarray:
    """Normalised Gaussian of length 3 * sigma, centred at index len // 2 (as the reference code builds it)."""
    fsize = 3 * int(sigma_bins)
    mu = fsize // 2
    i = np.arange(fsize, dtype=np.float64)
    k = np.exp(-0.5 * (i - mu) ** 2 / float(sigma_bins) ** 2)
    return (k / k.sum()).astype(np.float32)


#: Rows (azimuths) processed together: ~15 KB per row per buffer, so one block's scratch arrays stay in the
#: L2 cache between the ~15 element-wise passes (measured ~20 % less CPU than whole-scan passes).
_BLOCK_ROWS = 64


class _Workspace:
    """Scratch arrays reused across calls (~14 MB for a 400 x 3,768 scan).

    Fresh multi-megabyte temporaries cost more in page faults than the arithmetic itself (~4,000 minor
    faults and ~2x the run time per Oxford scan measured without reuse), so the hot path writes into
    these buffers instead.
    """

    def __init__(self, shape: tuple[int, int]) -> None:
        n_az, n_bins = shape
        self.shape = shape
        block = (min(_BLOCK_ROWS, n_az), n_bins)
        self.q = np.empty(block, np.float32)
        self.p = np.empty(block, np.float32)
        self.d = np.empty(block, np.float32)
        self.e = np.empty(block, np.float32)
        self.f = np.empty(block, np.float32)
        self.mask_u8 = np.empty(block, np.uint8)
        self.qn = np.empty(block, np.float32)  # q / sigma_q of a response on the first bins only
        self.y = np.empty(shape, np.float32)
        self.kept = np.empty(shape, bool)
        self.padded = np.zeros((n_az, n_bins + 2), np.int8)
        self.edges = np.empty(n_az * (n_bins + 2) - 1, np.int8)
        self.edge_mask = np.empty(n_az * (n_bins + 2) - 1, bool)


def _leading(buf: np.ndarray, rows: int, width: int) -> np.ndarray:
    """A contiguous (rows, width) array over the start of scratch buffer ``buf`` (width <= its own)."""
    return buf.reshape(-1)[: rows * width].reshape(rows, width)


_shared_ws: _Workspace | None = None
_shared_lock = threading.Lock()


@contextmanager
def _workspace(shape: tuple[int, int]) -> Iterator[_Workspace]:
    """One shared workspace (bounded memory under a threaded server); a busy one -> a private one."""
    global _shared_ws
    if not _shared_lock.acquire(blocking=False):
        yield _Workspace(shape)
        return
    try:
        if _shared_ws is None or _shared_ws.shape != shape:
            _shared_ws = _Workspace(shape)
        yield _shared_ws
    finally:
        _shared_lock.release()


def _response_into(s: np.ndarray, config: Cen2018Config, ws: _Workspace, width: int | None = None,
                   y: np.ndarray | None = None) -> np.ndarray:
    """Compute the normalised response y / sigma_q into ``ws.y`` (or ``y``); returns sigma_q (A,) float64.

    The published formulas are evaluated on q / sigma_q and p / sigma_q (p is linear in q, so p / sigma_q is
    the filtered q / sigma_q): every term then has unit scale, y / sigma_q > z_q is the detection test, and
    no per-row broadcasting is needed after the first two steps. Rows are processed in blocks of
    ``_BLOCK_ROWS`` (every step is per row, so blocking changes no result).

    With ``width`` (< R) only the first ``width`` bins of y are computed, into the contiguous (A, width)
    ``y``: the row statistics (mean, sigma_q) still use whole rows, and every bin of y depends only on the
    bins within the Gaussian's half length of it, so y is the same as the whole row's except in the last
    half kernel (+ the element-wise ops' scalar tails) of the width, which the caller discards.
    """
    kernel = _gaussian_kernel(config.sigma_bins).reshape(1, -1)
    sigma_all = np.empty(s.shape[0], dtype=np.float64)
    narrow = width is not None and width < s.shape[1]
    for r0 in range(0, s.shape[0], _BLOCK_ROWS):
        r1 = min(r0 + _BLOCK_ROWS, s.shape[0])
        n = r1 - r0
        if narrow:
            assert width is not None and y is not None
            sigma_all[r0:r1] = _response_block(
                s[r0:r1], kernel, ws.q[:n], _leading(ws.p, n, width), ws.d[:n], _leading(ws.e, n, width),
                _leading(ws.f, n, width), ws.mask_u8[:n], y[r0:r1], qn=_leading(ws.qn, n, width))
        else:
            sigma_all[r0:r1] = _response_block(s[r0:r1], kernel, ws.q[:n], ws.p[:n], ws.d[:n], ws.e[:n],
                                               ws.f[:n], ws.mask_u8[:n], ws.y[r0:r1] if y is None else y[r0:r1])
    return sigma_all


def _response_block(s: np.ndarray, kernel: np.ndarray, q: np.ndarray, p: np.ndarray, d: np.ndarray,
                    nqp: np.ndarray, npp: np.ndarray, mask_u8: np.ndarray, y: np.ndarray,
                    qn: np.ndarray | None = None) -> np.ndarray:
    """One block of rows: y / sigma_q into ``y`` using the scratch arrays; returns the rows' sigma_q.

    ``q``, ``d`` and ``mask_u8`` span whole rows (the row statistics); with ``qn`` (contiguous, narrower),
    the response is computed on its first bins only: ``p``, ``nqp``, ``npp`` and ``y`` then have its shape.
    """
    # float64 accumulation for the row means; everything per bin stays float32 (as the reference code).
    mean = cv2.reduce(s, 1, cv2.REDUCE_AVG, dtype=cv2.CV_64F).astype(np.float32)
    np.subtract(s, mean, out=q)

    # sigma_q = sqrt(sum_{q<0} 2 q^2 / count(q<0)) per azimuth; 0.034 where no bin is negative (reference).
    cv2.threshold(q, 0.0, 0.0, cv2.THRESH_TOZERO_INV, dst=d)  # min(q, 0)
    sum_sq = 2.0 * np.einsum("ij,ij->i", d, d).astype(np.float64)
    cv2.compare(q, 0.0, cv2.CMP_LT, dst=mask_u8)  # type: ignore[call-overload]  # scalar src2 is valid
    n_neg = cv2.reduce(mask_u8, 1, cv2.REDUCE_SUM, dtype=cv2.CV_32S).ravel() // 255
    sigma_q = np.full(q.shape[0], _SIGMA_Q_FALLBACK, dtype=np.float64)
    has_neg = (n_neg > 0) & (sum_sq > 0)
    sigma_q[has_neg] = np.sqrt(sum_sq[has_neg] / n_neg[has_neg])

    if qn is None:
        np.multiply(q, (1.0 / sigma_q).astype(np.float32)[:, None], out=q)  # q / sigma_q
    else:  # the first bins only (each product is the same number)
        np.multiply(q[:, : qn.shape[1]], (1.0 / sigma_q).astype(np.float32)[:, None], out=qn)
        q, d = qn, _leading(d, qn.shape[0], qn.shape[1])  # d's whole-row values are no longer needed
    # Anchor at index len // 2 as the reference (OpenCV's default anchor for odd lengths such as 51).
    cv2.filter2D(q, cv2.CV_32F, kernel, dst=p, anchor=(kernel.shape[1] // 2, 0), delta=0.0,
                 borderType=cv2.BORDER_REFLECT_101)  # p / sigma_q
    cv2.subtract(q, p, dst=d)  # (q - p) / sigma_q
    cv2.multiply(d, d, dst=nqp, scale=-0.5)
    cv2.exp(nqp, dst=nqp)  # nqp = exp(-0.5 ((q - p) / sigma_q)^2)
    cv2.multiply(p, p, dst=npp, scale=-0.5)
    cv2.exp(npp, dst=npp)  # npp = exp(-0.5 (p / sigma_q)^2)
    # y = q (1 - nqp) + p (nqp - npp) = q - nqp (q - p) - p npp, all divided by sigma_q.
    cv2.multiply(nqp, d, dst=d)
    cv2.subtract(q, d, dst=y)
    cv2.multiply(p, npp, dst=npp)
    cv2.subtract(y, npp, dst=y)
    return sigma_q


def cen2018_response(power: np.ndarray, config: Cen2018Config = Cen2018Config()) -> tuple[np.ndarray, np.ndarray]:
    """The Cen 2018 signal y and the per-azimuth threshold z_q * sigma_q for an (A, R) power array.

    Args:
        power: (A, R) float32 power in [0, 1].
        config: detector parameters (only ``z_q`` and ``sigma_bins`` are used here).

    Returns:
        y: (A, R) float32 detector response (a new array).
        threshold: (A,) float32 z_q * sigma_q per azimuth.
    """
    s = np.ascontiguousarray(power, dtype=np.float32)
    ws = _Workspace(s.shape)  # not the shared one: the caller keeps y
    sigma_q = _response_into(s, config, ws)
    return ws.y * sigma_q.astype(np.float32)[:, None], (config.z_q * sigma_q).astype(np.float32)


#: bins computed beyond the last one a range-limited detection needs: the Gaussian's half length is added
#: to this; it also keeps the element-wise OpenCV ops' scalar tails (at most one SIMD width) out of the bins used
_NARROW_MARGIN_BINS = 64


def _runs(kept: np.ndarray, padded: np.ndarray, edges: np.ndarray,
          edge_mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(row, middle column) of every run of True in the (A, W) ``kept``, row-major; ``padded`` (A, W + 2),
    ``edges`` and ``edge_mask`` (A (W + 2) - 1,) are scratch."""
    # One False column each side of every row, so each run has a start and an end and no run crosses rows;
    # then the flat rising/falling edges give the runs.
    padded[:, 0] = 0
    padded[:, -1] = 0
    padded[:, 1:-1] = kept
    flat = padded.reshape(-1)
    np.subtract(flat[1:], flat[:-1], out=edges)
    starts = np.flatnonzero(np.equal(edges, 1, out=edge_mask))
    ends = np.flatnonzero(np.equal(edges, -1, out=edge_mask))  # one past the run's last element
    stride = padded.shape[1]
    row = starts // stride
    start_col = starts % stride  # edge index k -> padded column k % stride + 1 -> scan column k % stride
    col = start_col + (ends - starts) // 2  # middle element (index len // 2), as the reference code
    return row, col


def detect_landmarks(scan: RadarScan, config: Cen2018Config | None = None,
                     max_range_m: float | None = None) -> Landmarks:
    """Detect Cen 2018 landmarks on a polar scan.

    Args:
        scan: the polar scan (power (A, R) in [0, 1]); azimuths flagged invalid yield no keypoints.
        config: detector parameters; ``None`` uses the defaults with the preset's minimum range.
        max_range_m: when given, only the landmarks with ``range_m <= max_range_m`` are returned: exactly
            those of the detection without it (same values, same order). The response is then computed only
            as far out as they need (e.g. ~45 % of a Boreas scan for the descriptor model's 128 m image), and
            again over whole rows for the rows where a run of detections reaches the computed bins' edge.

    Returns:
        ``Landmarks`` (positions in the scan's sensor frame, metres). Without a cap they are sorted by
        azimuth row then range bin; with ``max_keypoints`` the strongest come first.
    """
    require_scan(scan, "detect_landmarks")
    if max_range_m is not None and not (math.isfinite(float(max_range_m)) and max_range_m >= 0):
        raise ConfigError(f"max_range_m must be a finite range >= 0 in metres (None: the whole scan), got "
                          f"{max_range_m}")
    config = config or Cen2018Config()
    min_range = config.min_range_bins
    if min_range is None:
        min_range = get_preset(scan.preset).landmark_min_range_bins if scan.preset else 0
    n_az, n_bins = scan.power.shape
    min_range = int(min(min_range, n_bins))

    # bins a range-limited detection computes: every landmark within the range is the middle of a run that
    # ends before bin ``valid - 1`` unless its row has a detection there (those rows: whole rows, below)
    valid = n_bins
    if max_range_m is not None and config.max_keypoints is None and scan.range_resolution_m > 0:
        last = math.floor((float(max_range_m) - scan.range_offset_m) / scan.range_resolution_m) + 1
        valid = max(min_range, last, 0) + 2
    width = valid + 3 * int(config.sigma_bins) // 2 + _NARROW_MARGIN_BINS
    if width >= n_bins:
        valid = width = n_bins

    s = np.ascontiguousarray(scan.power, dtype=np.float32)
    if jit_enabled() and n_az > 0 and n_bins > 0:
        # the compiled detector: y only where it decides (``cen2018_kernels``; equal up to float32 rounding)
        band = certain_band(float(config.z_q))
        row, col, strength = detect_rows(s, np.ascontiguousarray(scan.valid, dtype=bool),
                                         _gaussian_kernel(config.sigma_bins), float(config.z_q), min_range,
                                         valid, _SIGMA_Q_FALLBACK, band[0], band[1])
    else:
        row, col, strength = _detect_vectorised(s, scan.valid, config, min_range, valid, width)
    if config.max_keypoints is not None and row.size > config.max_keypoints:
        order = np.argsort(-strength, kind="stable")[: config.max_keypoints]
        row, col, strength = row[order], col[order], strength[order]

    azimuth_rad = scan.azimuths[row]
    range_m = scan.range_offset_m + col * scan.range_resolution_m
    if max_range_m is not None:
        near = range_m <= max_range_m
        row, col, strength, azimuth_rad, range_m = row[near], col[near], strength[near], azimuth_rad[near], \
            range_m[near]
    xy = polar_to_metric(azimuth_rad, range_m)
    return Landmarks(
        azimuth_index=row.astype(np.int64),
        range_bin=col.astype(np.int64),
        azimuth_rad=azimuth_rad.astype(np.float64),
        range_m=range_m.astype(np.float64),
        xy_m=xy.reshape(-1, 2),
        strength=strength,
    )


def _detect_vectorised(s: np.ndarray, valid_rows: np.ndarray, config: Cen2018Config, min_range: int, valid: int,
                       width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows, middle bins and strengths of the runs (row-major) with the vectorised response: bins up to
    ``width`` computed, ``min_range:valid`` tested, whole rows again where a run reaches ``valid - 1``."""
    n_az, n_bins = s.shape
    with _workspace(s.shape) as ws:
        y = _leading(ws.y, n_az, width)
        sigma_q = _response_into(s, config, ws, width, y)
        kept = _leading(ws.kept, n_az, valid)
        np.greater(y[:, :valid] if valid < width else y, config.z_q, out=kept)
        kept[:, :min_range] = False
        kept[~valid_rows] = False
        # rows where a run of detections reaches the last computed bin may continue past it: those rows again,
        # whole (their row statistics and every bin are the same numbers as in the whole scan's pass)
        longer = np.flatnonzero(kept[:, valid - 1]) if valid < n_bins else np.zeros(0, np.int64)
        kept[longer] = False
        row, col = _runs(kept, _leading(ws.padded, n_az, valid + 2), ws.edges[: n_az * (valid + 2) - 1],
                         ws.edge_mask[: n_az * (valid + 2) - 1])
        strength = (y[row, col] * sigma_q[row]).astype(np.float32)
    if len(longer):
        sub = s[longer]
        wx = _Workspace(sub.shape)
        sigma_x = _response_into(sub, config, wx)
        kept_x = np.greater(wx.y, config.z_q, out=wx.kept)
        kept_x[:, :min_range] = False  # (invalid rows were never among them)
        row_x, col_x = _runs(kept_x, wx.padded, wx.edges, wx.edge_mask)
        strength_x = (wx.y[row_x, col_x] * sigma_x[row_x]).astype(np.float32)
        order = np.argsort(np.concatenate([row, longer[row_x]]), kind="stable")  # row-major again
        row = np.concatenate([row, longer[row_x]])[order]
        col = np.concatenate([col, col_x])[order]
        strength = np.concatenate([strength, strength_x])[order]
    return row, col, strength
