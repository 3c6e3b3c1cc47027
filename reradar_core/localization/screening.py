"""Landmark-alignment screen of many candidate keyframes at once (vectorised ``screen_alignment``).

``reradar_core.matching.screen_alignment`` scores one keyframe: pair each of ~256 query landmarks with its 5
most similar keyframe landmarks (local descriptors), draw 1,500 two-point minimal sets, keep those whose
lengths agree, and count the query landmarks each hypothesis puts within ``score_threshold_m`` of a keyframe
landmark. Per candidate that is a 256 x M similarity product, a top-k, ~150 surviving hypotheses and a table
look-up - each too small for numpy to be efficient, so 20-60 candidates cost 1.5 ms each in Python overhead.

Here the same steps run once for all candidates: one batched similarity product and top-k, minimal sets drawn
once (the pair lists of all candidates have the same length, so one seeded draw indexes every candidate), and
one look-up into compact per-keyframe alignment masks (``ScreenGrid``: 1 where a keyframe landmark is within
``score_threshold_m``, bit-packed: ~10 KB per keyframe instead of a ~0.3 MB float32 distance grid). The scores follow
the single-candidate definition; the pair lists, the seeded draw and the arithmetic are those of
``screen_alignment``, so the scores are the same (tested).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from reradar_core.jit import jit_enabled
from reradar_core.matching import AlignmentConfig, build_landmark_grid, screen_alignment
from reradar_core.matching.alignment import topk_last_axis
from reradar_core.matching.kernels import (
    PAIR_BORDERLINE,
    PAIR_CONSISTENT,
    best_aligned_screen,
    consistent_pairs_screen,
)

__all__ = ["ScreenGrid", "build_screen_grid", "ScreenKeyframe", "screen_keyframe", "screen_candidates"]


@dataclass
class ScreenGrid:
    """Alignment mask of one keyframe's landmarks.

    Attributes:
        packed: ``np.packbits`` of the (n * n,) row-major mask (row = y cell, column = x cell): 1 where a
            keyframe landmark is within the score threshold of the cell. Points outside the grid are never
            near (the grid covers the landmarks plus a margin larger than the threshold).
        n: cells per side; origin_m: lower corner (same for x and y), metres; cell_m: cell size, metres.
    """

    packed: np.ndarray
    n: int
    origin_m: float
    cell_m: float

    @property
    def near(self) -> np.ndarray:
        """The (n * n,) uint8 mask (0 / 1)."""
        return np.unpackbits(self.packed, count=self.n * self.n)


def build_screen_grid(points_xy_m: np.ndarray, config: AlignmentConfig) -> ScreenGrid:
    """The ``ScreenGrid`` of (M, 2) landmark positions (metres): the cells of ``build_landmark_grid`` whose
    distance to the nearest landmark is below ``config.score_threshold_m``."""
    grid = build_landmark_grid(points_xy_m, config.grid_cell_m)
    near = (grid.distance_m < config.score_threshold_m).reshape(-1)
    return ScreenGrid(np.packbits(near), int(grid.distance_m.shape[0]), float(grid.origin_m), float(grid.cell_m))


@dataclass
class ScreenKeyframe:
    """What the screen needs of one keyframe: (M, 2) landmarks (metres, its sensor frame; any float dtype),
    (M, C) unit local descriptors (any float dtype; the keyframe's own arrays, not copies) and its
    ``ScreenGrid``."""

    points: np.ndarray
    descriptors: np.ndarray
    grid: ScreenGrid


def _topk_indices(sim: np.ndarray, k: int) -> np.ndarray:
    """Indices of the k largest entries along the last axis of ``sim`` (any leading shape; overwritten), in
    ``torch.topk(sorted=False)``'s order like ``matching.alignment``: the pair order (which the seeded draw
    indexes) is then the same (``matching.topk_last_axis``)."""
    return topk_last_axis(sim, k)


def _cells(a: np.ndarray, b: np.ndarray, sign: float, t: np.ndarray, origin: np.ndarray,
           cell: np.ndarray, inverse: bool) -> np.ndarray:
    """floor(((a + sign * b) + t - origin) / cell) as int64, computed in place in ``a``; with ``inverse``,
    ``cell`` holds 1 / cell, a power of two, and the division is that multiplication (the same number:
    scaling by a power of two is exact)."""
    if sign < 0:
        a -= b
    else:
        a += b
    a += t
    a -= origin
    if inverse:
        a *= cell
    else:
        a /= cell
    np.floor(a, out=a)
    return a.astype(np.int64)


#: candidates whose descriptor similarities are computed at once (x 256 x ~512: ~5 MB float32)
_SIM_BLOCK = 10

#: hypotheses scored at once (x 128 scored landmarks: ~0.5 MB per float64 temporary)
_SCORE_BLOCK = 512


def _aligned_counts(sx: np.ndarray, sy: np.ndarray, c: np.ndarray, s: np.ndarray, tx: np.ndarray,
                    ty: np.ndarray, cand: np.ndarray, origins: np.ndarray, cells: np.ndarray, inverse: bool,
                    sizes: np.ndarray, offsets: np.ndarray, near: np.ndarray) -> np.ndarray:
    """(V,) scored landmarks ((P, 1) x, y) that V hypotheses (rotation cos / sin, translation, candidate) put
    on a cell of their candidate's alignment mask (``near``: every candidate's mask concatenated, last entry
    "outside"); ``cells`` (and ``inverse``) as ``_cells`` takes them."""
    # grid cell of every scored landmark under every hypothesis, (P, V): hypotheses along the contiguous axis,
    # so the per-hypothesis operands broadcast along long rows (fast); in place, in the arithmetic order of
    # ``LandmarkGrid.lookup`` (floor((x - origin) / cell)), so the cells are exactly the same
    go, gc = origins[cand], cells[cand]
    gi = _cells(sx * c, sy * s, -1.0, tx, go, gc, inverse)
    gj = _cells(sx * s, sy * c, 1.0, ty, go, gc, inverse)
    gn = sizes[cand]
    gnu = gn.astype(np.uint64)
    inside = gi.view(np.uint64) < gnu  # negative cells wrap to huge unsigned values
    inside &= gj.view(np.uint64) < gnu
    gj *= gn
    gj += gi
    gj += offsets[cand]
    np.putmask(gj, ~inside, len(near) - 1)
    hits = near[gj]
    if hits.shape[0] < 256:  # a uint8 sum cannot wrap: no cast per element
        return np.add.reduce(hits, axis=0, dtype=np.uint8).astype(np.int64)
    return hits.sum(axis=0, dtype=np.int64)


def screen_candidates(query_points: np.ndarray, query_descriptors: np.ndarray,
                      keyframes: Sequence[ScreenKeyframe], config: AlignmentConfig) -> np.ndarray:
    """Screen scores of many keyframes for one query, as ``screen_alignment`` defines them.

    Args:
        query_points: (N, 2) query landmarks, metres (query sensor frame).
        query_descriptors: (N, C) unit local descriptors (any float dtype).
        keyframes: the candidates.
        config: ``screen_source_points``, ``top_k_matches``, ``screen_hypotheses``, ``min_pair_separation_m``,
            ``max_length_mismatch_m``, ``score_points``, ``seed`` (and the grids' threshold / cell).

    Returns:
        (K,) float64 scores in [0, 1]: the best hypothesis' fraction of the (evenly subsampled
        ``score_points``) query landmarks within the threshold of a keyframe landmark; 0 for degenerate input.
    """
    out = np.zeros(len(keyframes))
    src = np.asarray(query_points, np.float64).reshape(-1, 2)
    n = len(src)
    if n < 2 or not np.all(np.isfinite(src)) or not keyframes:
        return out
    k = config.top_k_matches
    usable = [len(kf.points) >= k and bool(np.all(np.isfinite(kf.points))) for kf in keyframes]
    batch = [i for i, ok in enumerate(usable) if ok]
    for i, kf in enumerate(keyframes):  # too few landmarks for the shared pair layout (or bad): one at a time
        if not usable[i]:
            out[i] = screen_alignment(src, query_descriptors, kf.points, kf.descriptors, config)
    if not batch:
        return out
    sub = np.arange(0, n, max(1, n // config.screen_source_points))
    q = np.asarray(query_descriptors, np.float32)[sub]
    m_max = max(len(keyframes[i].points) for i in batch)
    kb = len(batch)
    desc = np.zeros((kb, m_max, q.shape[1]), np.float32)
    px = np.zeros((kb, m_max), np.float64)  # landmark x, y (metres): separate, so the gathers below are contiguous
    py = np.zeros((kb, m_max), np.float64)
    for row, i in enumerate(batch):
        m = len(keyframes[i].points)
        desc[row, :m] = keyframes[i].descriptors
        px[row, :m] = keyframes[i].points[:, 0]
        py[row, :m] = keyframes[i].points[:, 1]
    # one BLAS product per block of candidates (a batched np.matmul over a transposed view would not use BLAS).
    # Blocks, not all at once: 60 candidates x 256 x 512 similarities are a 31 MB temporary, and a request
    # thread's first allocation that large pays ~40 ms of fresh pages (the expanded queries were the tail).
    # Every similarity is its own 16-term dot product, so the blocks give the same numbers (checked against
    # one product on 600 random shapes) and the top-k is per row.
    num_pairs = len(sub) * k
    top = np.empty((kb, len(sub), k), np.int64)
    for lo in range(0, kb, _SIM_BLOCK):
        hi = min(kb, lo + _SIM_BLOCK)
        sim = (q @ desc[lo:hi].reshape((hi - lo) * m_max, -1).T).reshape(len(sub), hi - lo, m_max)  # (S, B, M)
        for row in range(lo, hi):  # padding never wins the top-k
            sim[:, row - lo, len(keyframes[batch[row]].points):] = -np.inf
        top[lo:hi] = _topk_indices(sim, k).transpose(1, 0, 2)
    # every candidate's pair list as a row (pair s * k + j: the j-th best match of source landmark s), as flat
    # indices of the paired keyframe landmarks into px / py (flattened: fx / fy)
    land = top.reshape(kb, num_pairs) + (np.arange(kb) * m_max)[:, None]
    fx, fy = px.reshape(-1), py.reshape(-1)

    # one seeded draw of minimal sets indexes every candidate's pair list (same length S * k for all)
    rng = np.random.default_rng(config.seed)
    a = rng.integers(0, num_pairs, config.screen_hypotheses)
    b = rng.integers(0, num_pairs, config.screen_hypotheses)
    s1, s2 = src[sub[a // k]], src[sub[b // k]]  # (H, 2), shared
    vs = s2 - s1
    ls = np.hypot(vs[:, 0], vs[:, 1])
    if jit_enabled():  # the same verdicts without the (K, H) gathers (``matching.kernels``)
        verdict = np.empty((kb, len(a)), np.int8)
        consistent_pairs_screen(land, a, b, fx, fy, ls, ls > config.min_pair_separation_m,
                                config.max_length_mismatch_m, verdict)
        edge = np.flatnonzero(verdict.reshape(-1) == PAIR_BORDERLINE)
        if len(edge):  # within the kernel's margin: the numpy expression decides
            g, h = np.divmod(edge, len(a))
            la, lb = land[g, a[h]], land[g, b[h]]
            ld = np.hypot(fx[lb] - fx[la], fy[lb] - fy[la])
            verdict.reshape(-1)[edge] = np.abs(ls[h] - ld) < config.max_length_mismatch_m
        sel = np.flatnonzero(verdict.reshape(-1) == PAIR_CONSISTENT)  # candidate-major order
        if len(sel) == 0:
            return out
        cand, hyp = np.divmod(sel, len(a))
        la, lb = land[cand, a[hyp]], land[cand, b[hyp]]
        d1x, d1y, d2x, d2y = fx[la], fy[la], fx[lb], fy[lb]
    else:
        la, lb = land[:, a], land[:, b]  # (K, H)
        d1x, d1y, d2x, d2y = fx[la], fy[la], fx[lb], fy[lb]
        vdx, vdy = d2x - d1x, d2y - d1y
        ld = np.hypot(vdx, vdy)
        ok = (ls > config.min_pair_separation_m)[None, :] & (np.abs(ls[None, :] - ld) < config.max_length_mismatch_m)
        sel = np.flatnonzero(ok)  # candidate-major order
        if len(sel) == 0:
            return out
        cand, hyp = np.divmod(sel, ok.shape[1])
        d1x, d1y, d2x, d2y = (d.reshape(-1)[sel] for d in (d1x, d1y, d2x, d2y))
    yaw = np.arctan2(d2y - d1y, d2x - d1x) - np.arctan2(vs[hyp, 1], vs[hyp, 0])
    c, s = np.cos(yaw), np.sin(yaw)
    ms = (s1[hyp] + s2[hyp]) / 2
    mdx = (d1x + d2x) / 2
    mdy = (d1y + d2y) / 2
    tx = mdx - (c * ms[:, 0] - s * ms[:, 1])
    ty = mdy - (s * ms[:, 0] + c * ms[:, 1])

    scored = src[:: max(1, n // config.score_points)]  # (P, 2)
    sx, sy = scored[:, 0:1], scored[:, 1:2]  # (P, 1)
    grids = [keyframes[i].grid for i in batch]
    sizes = np.array([g.n for g in grids], np.int64)
    origins = np.array([g.origin_m for g in grids])
    cells = np.array([g.cell_m for g in grids])
    with np.errstate(divide="ignore", over="ignore"):
        inv = 1.0 / cells
    # cells that are powers of two (0.5 m) with a finite inverse: multiply by it instead of dividing
    inverse = bool(np.all((cells > 0) & (np.frexp(cells)[0] == 0.5) & np.isfinite(inv)))
    if inverse:
        cells = inv
    if jit_enabled():  # one compiled loop, the same arithmetic (``matching.kernels``), on the packed masks
        packed = np.concatenate([g.packed for g in grids])
        bit_offsets = np.concatenate([[0], np.cumsum([len(g.packed) for g in grids])[:-1]]).astype(np.int64) * 8
        best = best_aligned_screen(np.ascontiguousarray(scored[:, 0]), np.ascontiguousarray(scored[:, 1]),
                                   c, s, tx, ty, cand, origins, cells, inverse, sizes, bit_offsets, packed, kb)
    else:
        offsets = np.concatenate([[0], np.cumsum(sizes * sizes)[:-1]])
        near = np.concatenate([g.near for g in grids] + [np.zeros(1, np.uint8)])  # last cell: "outside"
        counts = np.empty(len(cand), np.int64)  # aligned query landmarks per hypothesis
        # in blocks of hypotheses, so the (block, P) temporaries stay in the CPU cache (the arithmetic is
        # element-wise, so the cells - and the scores - do not depend on the block size)
        for lo in range(0, len(cand), _SCORE_BLOCK):
            sl = slice(lo, lo + _SCORE_BLOCK)
            counts[sl] = _aligned_counts(sx, sy, c[sl], s[sl], tx[sl], ty[sl], cand[sl], origins, cells,
                                         inverse, sizes, offsets, near)
        best = np.zeros(kb, np.int64)
        np.maximum.at(best, cand, counts)
    out[batch] = best / len(scored)
    return out


def screen_keyframe(features_points: np.ndarray, features_descriptors: np.ndarray,
                    config: AlignmentConfig) -> ScreenKeyframe:
    """A keyframe's ``ScreenKeyframe`` from its (M, 2) landmarks (metres) and (M, C) local descriptors."""
    pts = np.asarray(features_points).reshape(-1, 2)
    return ScreenKeyframe(pts, np.asarray(features_descriptors), build_screen_grid(pts, config))
