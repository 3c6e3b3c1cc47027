"""RaPlace: Radon sinogram of the Cartesian radar image, |FFT| along the offset axis, correlation matching.

References:
    H. Jang, M. Jung and A. Kim, "RaPlace: Place Recognition for Imaging Radar using Radon Transform and
    Mutable Threshold", IROS 2023.
    Reference implementation (the one the paper's baseline rows follow): OORD benchmark code,
    github.com/mttgdd/oord-dataset at commit f04683fb68d15f042395de528c92064dbfc4bc30:
    ``config/raplace.yaml`` (min_bin 60, max_bin 3768, cartesian, cart_res 1.2717 m, cart_pw 256),
    ``src/dataset.py`` + ``src/radar.py`` (Cartesian image), ``src/raplace.py`` (``SinoFFT``, ``RaPlace``),
    ``jobs/test_raplace.py``.

``raplace`` (the reference):
    1. bins < 60 zeroed; 256 x 256 px Cartesian image at 1.2717 m/px (``oord_cartesian_image``);
    2. Radon transform, angles 0..179 degrees, as ``skimage.transform.radon(circle=True)``: the image is
       rotated about pixel (128, 128) with bilinear interpolation (zero outside) and summed over rows, one
       column per angle -> (256 offsets, 180 angles); nothing is masked outside the inscribed circle;
    3. divided by its maximum, shrunk x0.25 as ``skimage.transform.rescale`` (Gaussian anti-aliasing with
       sigma 1.5 px, then bilinear zoom) -> (64, 45);
    4. ``|FFT|`` along the offset axis, the lower half of the rows kept *including the DC row* -> (32, 45);
    5. z-scored (mean 0, population std 1 over all 1,440 values);
    6. distance(q, i) = |max_s c_qq(s) - max_s c_qi(s)| with c_ab(s) = sum over angles of the circular
       cross-correlation of a and b along the *frequency* axis (shift s in frequency rows); the angle axis
       is not shifted, so the reference is not invariant to heading changes and gives no heading.

``raplace-nodc`` is the variant this project ran before (kept as a separately named method, not the
reference row): Cartesian image of the whole sweep, Radon over the inscribed disc, |FFT| without the DC row,
mean-removed and L2-normalised, similarity = max circular cross-correlation over *angle* shifts, which makes
it rotation-invariant and gives a heading (modulo 180 degrees).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from scipy import ndimage

from reradar_core.baselines.base import PlaceRecognitionMethod, Prepared
from reradar_core.baselines.oord import MAX_BIN, MIN_BIN, oord_cartesian_image
from reradar_core.geometry.cartesian import CartesianConfig, polar_to_cartesian
from reradar_core.io.scan import RadarScan

__all__ = ["RaPlaceConfig", "RaPlace", "RaPlaceNoDCConfig", "RaPlaceNoDC", "radon_skimage", "shrink_skimage",
           "sino_fft_descriptor", "radon_sinogram"]


@dataclass(frozen=True)
class RaPlaceConfig:
    """OORD ``config/raplace.yaml`` and ``src/raplace.py``: 256 px at 1.2717 m/px, 180 angles, x0.25 shrink."""

    cart_px: int = 256
    cart_res_m: float = 1.2717
    num_angles: int = 180
    scale: float = 0.25
    min_bin: int = MIN_BIN
    max_bin: int = MAX_BIN


def radon_skimage(image: np.ndarray, num_angles: int = 180) -> np.ndarray:
    """Radon transform as ``skimage.transform.radon(image, theta=arange(num_angles), circle=True)``.

    (W, W) image -> (W, num_angles) float64: column i = the image rotated by i degrees about pixel
    (W // 2, W // 2) (bilinear, zero outside), summed over rows. skimage rotates with the inverse map
    ``[[cos, sin, -c (cos + sin - 1)], [-sin, cos, -c (cos - sin - 1)]]`` in (column, row) coordinates; the
    same matrix is handed to ``cv2.warpAffine`` as an inverse map.
    """
    img = np.ascontiguousarray(image, dtype=np.float32)
    w = img.shape[0]
    if img.shape != (w, w):
        raise ValueError(f"radon_skimage needs a square image, got {img.shape}")
    c = w // 2
    out = np.empty((w, num_angles), dtype=np.float64)
    for i, a in enumerate(np.deg2rad(np.arange(num_angles, dtype=np.float64))):
        ca, sa = np.cos(a), np.sin(a)
        m = np.array([[ca, sa, -c * (ca + sa - 1)], [-sa, ca, -c * (ca - sa - 1)]], dtype=np.float64)
        rot = cv2.warpAffine(img, m, (w, w), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                             borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        out[:, i] = rot.sum(axis=0, dtype=np.float64)
    return out


def shrink_skimage(image: np.ndarray, scale: float) -> np.ndarray:
    """``skimage.transform.rescale(image, scale)`` for a 2-D float image and ``scale < 1``.

    Output shape ``round(shape * scale)``; Gaussian anti-aliasing with sigma ``(1 / s - 1) / 2`` per axis
    (s = output / input size), then linear ``scipy.ndimage.zoom`` with ``grid_mode=True``; both with
    mode ``mirror`` (skimage's default ``reflect``).
    """
    x = np.asarray(image, dtype=np.float64)
    out_shape = np.maximum(np.round(np.array(x.shape) * scale), 1).astype(int)
    factors = np.array(x.shape, dtype=np.float64) / out_shape
    sigma = np.maximum(0.0, (factors - 1.0) / 2.0)
    filtered = ndimage.gaussian_filter(x, sigma, mode="mirror")
    out = ndimage.zoom(filtered, out_shape / np.array(x.shape, dtype=np.float64), order=1, mode="mirror",
                       grid_mode=True)
    return np.clip(out, x.min(), x.max())


def sino_fft_descriptor(cart: np.ndarray, config: RaPlaceConfig = RaPlaceConfig()) -> np.ndarray:
    """Cartesian image -> (rows // 2, angles * scale) float64 z-scored |FFT| of the shrunk sinogram."""
    r = radon_skimage(cart, config.num_angles)
    peak = float(r.max())
    r = r / peak if peak > 0 else r
    r = shrink_skimage(r, config.scale)
    r = np.abs(np.fft.fft(r, axis=0))
    r = r[: r.shape[0] // 2]
    std = float(r.std())
    return (r - r.mean()) / (std if std > 0 else 1.0)


class RaPlace(PlaceRecognitionMethod):
    """The OORD benchmark's RaPlace (see the module docstring); no heading."""

    name = "raplace"
    algorithm_version = 2

    def __init__(self, config: RaPlaceConfig = RaPlaceConfig()) -> None:
        self.config = config

    def params(self) -> dict[str, Any]:
        c = self.config
        return {"px": c.cart_px, "res": c.cart_res_m, "angles": c.num_angles, "scale": c.scale,
                "min_bin": c.min_bin, "max_bin": c.max_bin}

    def prepare(self, scan: RadarScan) -> Prepared:
        c = self.config
        cart = oord_cartesian_image(scan.power, scan.range_resolution_m, c.cart_res_m, c.cart_px, c.min_bin,
                                    c.max_bin)
        return {"sino_fft": sino_fft_descriptor(cart, c).astype(np.float32)}

    def describe_prepared(self, prepared: Prepared) -> np.ndarray:
        return np.asarray(prepared["sino_fft"], dtype=np.float64)

    def build_index(self, db_descs: Any) -> Any:
        stack = np.stack([np.asarray(d, dtype=np.float64) for d in db_descs])  # (N, F, A)
        return np.conj(np.fft.rfft(stack, axis=1))  # (N, F//2+1, A)

    def _max_correlation(self, q_desc: np.ndarray, conj_spec: np.ndarray) -> np.ndarray:
        """(N,) max over frequency shifts of the angle-summed circular cross-correlation."""
        q = np.asarray(q_desc, dtype=np.float64)
        cross = np.einsum("fa,nfa->nf", np.fft.rfft(q, axis=0), conj_spec)
        return np.fft.irfft(cross, n=q.shape[0], axis=1).max(axis=1)

    def distance(self, q_desc: np.ndarray, index: Any) -> np.ndarray:
        q = np.asarray(q_desc, dtype=np.float64)
        auto = self._max_correlation(q, np.conj(np.fft.rfft(q, axis=0))[None])[0]
        return np.abs(auto - self._max_correlation(q, index))


# ---------------------------------------------------------------------------------------------- variant
@dataclass(frozen=True)
class RaPlaceNoDCConfig:
    """The earlier variant: 256 px image of the whole sweep (``max_range_m`` None), 180 angles."""

    image_px: int = 256
    num_angles: int = 180
    max_range_m: float | None = None


def radon_sinogram(image: np.ndarray, num_angles: int = 180) -> np.ndarray:
    """Radon transform over the inscribed disc: (num_angles, W) float32, angle i = i * 180 / num_angles deg.

    Row i holds the line integrals perpendicular to direction theta_i (image rotated by theta_i about its
    centre, columns summed); one ``cv2.warpAffine`` per angle.
    """
    img = np.ascontiguousarray(image, dtype=np.float32)
    w = img.shape[0]
    c = (w - 1) / 2.0
    yy, xx = np.mgrid[0:w, 0:w]
    img = img * (((yy - c) ** 2 + (xx - c) ** 2) <= c * c)  # disc: every angle sees the same support
    out = np.empty((num_angles, w), dtype=np.float32)
    for i in range(num_angles):
        m = cv2.getRotationMatrix2D((c, c), 180.0 * i / num_angles, 1.0)
        out[i] = cv2.warpAffine(img, m, (w, w), flags=cv2.INTER_LINEAR).sum(axis=0)
    return out


class RaPlaceNoDC(PlaceRecognitionMethod):
    """Radon + |FFT| without the DC row, max circular cross-correlation over angle shifts; gives a heading.

    The heading is known modulo 180 degrees (a projection at theta + 180 is the one at theta mirrored in
    offset, which |FFT| cannot tell apart) and reported in [-90, 90) degrees.
    """

    name = "raplace-nodc"
    provides_heading = True

    def __init__(self, config: RaPlaceNoDCConfig = RaPlaceNoDCConfig()) -> None:
        self.config = config

    def params(self) -> dict[str, Any]:
        return {"px": self.config.image_px, "angles": self.config.num_angles,
                "range": self.config.max_range_m, "v": 1}

    def prepare(self, scan: RadarScan) -> Prepared:
        max_r = self.config.max_range_m or float(scan.ranges_m[-1])
        cfg = CartesianConfig(self.config.image_px, 2.0 * max_r / self.config.image_px)
        sino = radon_sinogram(polar_to_cartesian(scan, cfg), self.config.num_angles)
        # |FFT| along the offset: translation-robust. The DC term (total image mass, equal at every angle)
        # carries neither place nor rotation information, so it is dropped.
        mag = np.abs(np.fft.rfft(sino, axis=1))[:, 1:].astype(np.float32)
        mag -= mag.mean()
        mag /= max(float(np.linalg.norm(mag)), 1e-12)
        return {"radon_fft": mag}

    def describe_prepared(self, prepared: Prepared) -> np.ndarray:
        return np.asarray(prepared["radon_fft"], dtype=np.float32)

    def build_index(self, db_descs: Any) -> Any:
        stack = np.stack([np.asarray(d, dtype=np.float32) for d in db_descs])  # (N, T, K)
        return np.conj(np.fft.rfft(stack, axis=1)).astype(np.complex64)  # (N, T//2+1, K)

    def _correlation(self, q_desc: np.ndarray, index: Any) -> np.ndarray:
        """(N, T) circular cross-correlation c[n, s] = sum_{t,k} Q[t, k] D_n[t - s, k] (normalised, [-1, 1])."""
        qf = np.fft.rfft(np.asarray(q_desc, dtype=np.float32), axis=0).astype(np.complex64)  # (T//2+1, K)
        cross = np.einsum("tk,ntk->nt", qf, index)
        return np.fft.irfft(cross, n=self.config.num_angles, axis=1)

    def distance(self, q_desc: np.ndarray, index: Any) -> np.ndarray:
        return 1.0 - self._correlation(q_desc, index).max(axis=1).astype(np.float64)

    def estimate_heading(self, q_desc: np.ndarray, index: Any, j: int) -> float | None:
        corr = self._correlation(q_desc, index[j : j + 1])[0]
        s = int(np.argmax(corr))
        step_deg = 180.0 / self.config.num_angles
        deg = (s * step_deg + 90.0) % 180.0 - 90.0  # modulo-180 ambiguity -> [-90, 90)
        return float(np.deg2rad(deg))
