"""Scan preprocessing of the OORD benchmark code, shared by RingKey, RaPlace, RadVLAD and ResNet18-NetVLAD.

Reference: M. Gadd et al., OORD benchmark code, github.com/mttgdd/oord-dataset at commit
f04683fb68d15f042395de528c92064dbfc4bc30, ``src/dataset.py`` (``Dataset.load_image``), ``src/radar.py``
(``radar_polar_to_cartesian``) and ``config/{ringkey,raplace,radvlad,resnet18_netvlad}.yaml``:

1. power in [0, 1] (the PNG byte / 255, which is what ``RadarScan.power`` holds);
2. range bins below ``min_bin = 60`` are set to zero ("suppress early returns") and bins from
   ``max_bin = 3768`` on are cut off;
3. polar methods: the (A, R) image is resized with Pillow's default filter (bicubic, antialiased when
   shrinking) to ``num_azis`` rows x ``num_bins`` columns; Cartesian methods: the polar image is mapped to a
   square image of ``cart_pw`` pixels at ``cart_res`` metres per pixel by bilinear ``cv2.remap``, sampling
   range bin ``u = (r - res / 2) / res`` and azimuth row ``v = theta / (2 pi / A)`` with the first and last
   azimuth wrapped around.

The cut-offs are in range bins, as in the reference (60 bins = 2.6 m on the OORD radar's 0.0432 m bins).
"""

from __future__ import annotations

import cv2
import numpy as np
from PIL import Image

__all__ = ["MIN_BIN", "MAX_BIN", "suppress_range", "oord_polar_image", "oord_cartesian_image"]

#: ``min_bin`` / ``max_bin`` of every OORD benchmark config.
MIN_BIN = 60
MAX_BIN = 3768


def suppress_range(power: np.ndarray, min_bin: int = MIN_BIN, max_bin: int = MAX_BIN) -> np.ndarray:
    """(A, R) polar power -> (A, min(R, max_bin)) float32 copy with bins ``< min_bin`` set to zero."""
    p = np.array(np.asarray(power, dtype=np.float32)[:, :max_bin], dtype=np.float32)
    p[:, :min_bin] = 0.0
    return p


def oord_polar_image(power: np.ndarray, num_azis: int, num_bins: int, min_bin: int = MIN_BIN,
                     max_bin: int = MAX_BIN) -> np.ndarray:
    """(A, R) polar power -> (num_azis, num_bins) float32, as ``Dataset.load_image`` with ``cartesian: False``.

    The resize is Pillow's ``Image.resize`` with its default filter (bicubic; Pillow widens the kernel by
    the shrink factor, so every input bin contributes) on a 32-bit float image.
    """
    img = Image.fromarray(suppress_range(power, min_bin, max_bin))  # 32-bit float image (mode "F")
    return np.asarray(img.resize((num_bins, num_azis), Image.Resampling.BICUBIC), dtype=np.float32)


def oord_cartesian_image(power: np.ndarray, range_resolution_m: float, cart_res_m: float, cart_pw: int,
                         min_bin: int = MIN_BIN, max_bin: int = MAX_BIN) -> np.ndarray:
    """(A, R) polar power -> (cart_pw, cart_pw) float32 Cartesian image, as ``radar_polar_to_cartesian``.

    Image layout of the reference: row 0 is ``+x`` (forward) at ``+cart_min_range``, column 0 is
    ``y = -cart_min_range``; pixel angle ``atan2(y, x)`` in [0, 2 pi) indexes the azimuth rows as
    ``theta / (2 pi / A)`` (azimuth row 0 at 0 rad, uniform steps, as the reference's ``load_radar``); bins
    beyond the scan's range read as zero.

    Args:
        power: (A, R) polar power in [0, 1].
        range_resolution_m: metres per range bin.
        cart_res_m: metres per Cartesian pixel (RaPlace: 1.2717).
        cart_pw: image side in pixels (RaPlace: 256).
    """
    polar = suppress_range(power, min_bin, max_bin)
    n_az = polar.shape[0]
    if cart_pw % 2 == 0:
        cart_min_range = (cart_pw / 2 - 0.5) * cart_res_m
    else:
        cart_min_range = cart_pw // 2 * cart_res_m
    coords = np.linspace(-cart_min_range, cart_min_range, cart_pw, dtype=np.float32)
    y, x = np.meshgrid(coords, -coords)
    sample_range = np.sqrt(y * y + x * x)
    sample_angle = np.arctan2(y, x)
    sample_angle += (sample_angle < 0).astype(np.float32) * np.float32(2.0 * np.pi)
    u = (sample_range - range_resolution_m / 2.0) / range_resolution_m
    u[u < 0] = 0
    # azimuth rows padded with the last row in front and the first row behind: the crossover interpolates
    v = sample_angle / np.float32(2.0 * np.pi / n_az) + 1.0
    padded = np.concatenate((polar[-1:], polar, polar[:1]), axis=0)
    return cv2.remap(padded, u.astype(np.float32), v.astype(np.float32), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
