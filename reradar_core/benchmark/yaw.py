"""Controlled yaw-rotation consistency of the local feature map F' (paper, "Controlled Yaw-Rotation
Evaluation").

For a scan's Cartesian image I and a yaw theta: F = f(I), F_theta = f(R_theta I), and the inverse-aligned
map F~ = R_-theta(F_theta). S(theta) is the mean cosine similarity between F(p) and F~(p) over locations p
inside the inscribed disc (rotation padding and cropping excluded) where F(p) is not zero, averaged over
scans. A score near 1 means
the feature map is rotation-equivariant.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from reradar_core.io.scan import RadarScan

__all__ = ["rotate_image", "yaw_consistency"]


def rotate_image(x: torch.Tensor, theta_rad: float) -> torch.Tensor:
    """Rotate (B, C, H, W) maps by ``theta_rad`` about the centre ((W - 1) / 2), bilinear, zero padding."""
    c, s = float(np.cos(theta_rad)), float(np.sin(theta_rad))
    mat = torch.tensor([[c, -s, 0.0], [s, c, 0.0]], dtype=x.dtype)[None].expand(x.shape[0], 2, 3)
    grid = F.affine_grid(mat, list(x.shape), align_corners=True)
    return F.grid_sample(x, grid, mode="bilinear", padding_mode="zeros", align_corners=True)


def yaw_consistency(extractor: Any, scans: Sequence[RadarScan], angles_deg: np.ndarray) -> np.ndarray:
    """(len(angles),) mean cosine consistency S(theta) of ``extractor``'s F' over ``scans``."""
    imgs = torch.from_numpy(np.stack([extractor.cartesian_image(s) for s in scans]).astype(np.float32))[:, None]
    _, f0 = extractor.run_images(imgs[:, 0].numpy())
    f0 = torch.from_numpy(f0)
    h = f0.shape[-1]
    cc = (h - 1) / 2.0
    yy, xx = torch.meshgrid(torch.arange(h), torch.arange(h), indexing="ij")
    mask = ((yy - cc) ** 2 + (xx - cc) ** 2) <= (cc - 1.0) ** 2
    # cosine is undefined where the unrotated map is zero (no signal at all): leave those locations out
    norm = f0.norm(dim=1)
    valid = mask[None] & (norm > 1e-6 * float(norm.max()))
    out = np.zeros(len(angles_deg))
    for i, a in enumerate(angles_deg):
        th = float(np.deg2rad(a))
        _, ft = extractor.run_images(rotate_image(imgs, th)[:, 0].numpy())
        back = rotate_image(torch.from_numpy(ft), -th)
        cos = F.cosine_similarity(f0, back, dim=1, eps=1e-8)  # (B, h, w)
        out[i] = float(cos[valid].mean())
    return out
