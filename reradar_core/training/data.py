"""Training data: cached Cartesian images, pose-based tuple sampling, yaw/translation augmentation.

Each training sequence is rendered once to a float16 stack of *oversized* Cartesian images (side
``model width + 2 * margin``, same 0.64 m/px, sensor at the centre) under ``cache_dir("training", ...)``; a
training sample is a rotated / shifted crop of it (``crop_view``), so random-yaw augmentation never shows
empty corners. Validation uses the centre crop, which equals ``polar_to_cartesian`` at the model's size
pixel for pixel.

Sequences are grouped by place: poses of sequences in the same group share a world frame (traversals of one
route), so positives / negatives are decided by distance within a group; scans of different groups are
always negatives.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from reradar_core.errors import ConfigError
from reradar_core.geometry.cartesian import CartesianConfig, polar_to_cartesian
from reradar_core.paths import CACHE_SOURCE_FILE, cache_dir

__all__ = ["CachedSequence", "TrainingSet", "TupleSampler", "cache_sequence", "crop_view", "sequence_group"]

logger = logging.getLogger(__name__)

CACHE_VERSION = 1


@dataclass
class CachedSequence:
    """Oversized Cartesian images of one sequence plus its poses.

    Attributes:
        name: sequence name; group: place group (shared world frame).
        images: (N, S, S) float16 (memory-mapped), S = big side in px.
        poses: (N, 3) T_world_sensor (x, y, yaw), metres / radians.
        resolution_m: metres per pixel.
    """

    name: str
    group: str
    images: np.ndarray
    poses: np.ndarray
    resolution_m: float

    def __len__(self) -> int:
        return len(self.poses)

    def fraction(self, start: float, stop: float) -> CachedSequence:
        """The scans in [start, stop) of the sequence (fractions of its length; a memory-mapped view)."""
        n = len(self.poses)
        a, b = int(round(start * n)), int(round(stop * n))
        if b <= a:
            raise ConfigError(f"empty fraction [{start}, {stop}) of sequence {self.name} ({n} scans)")
        if (a, b) == (0, n):
            return self
        return CachedSequence(f"{self.name}[{a}:{b}]", self.group, self.images[a:b], self.poses[a:b],
                              self.resolution_m)


def sequence_group(seq) -> str:
    """Place group of a sequence: the simulator's route id from ``reradar_sim.json`` when present, else the
    sequence name (only scans of the same sequence are then compared by distance)."""
    meta_path = Path(getattr(seq, "root", "")) / "reradar_sim.json"
    if meta_path.is_file():
        try:
            meta = json.loads(meta_path.read_text())
        except json.JSONDecodeError:
            meta = {}
        for key in ("route", "route_name", "place_group", "world"):
            if key in meta and meta[key]:
                return str(meta[key])
    return str(seq.name)


def _cache_key(seq, big: CartesianConfig) -> str:
    first, last = seq.scan_paths[0], seq.scan_paths[-1]
    stat = (first.stat().st_mtime_ns, last.stat().st_size) if first.exists() else (0, 0)
    # the preset (range bin size) and the poses (a pose file read in another time unit) change what is cached
    poses = hashlib.sha1(np.ascontiguousarray(seq.poses.poses, dtype=np.float64).tobytes()).hexdigest()
    h = hashlib.sha1(json.dumps([CACHE_VERSION, str(Path(seq.root).resolve()), len(seq), str(first), str(last),
                                 stat, big.width_px, big.resolution_m, seq.preset.name, poses]).encode())
    return h.hexdigest()[:16]


def cache_sequence(seq, width_px: int = 201, resolution_m: float = 0.64, margin_px: int = 80,
                   group: str | None = None, progress: bool = True) -> CachedSequence:
    """Render (once) and memory-map the oversized Cartesian images of ``seq`` (``io.datasets.Sequence``).

    Args:
        width_px: the model's input side; the cache side is ``width_px + 2 * margin_px`` (margin 80: any
            rotation of a 201 px crop (half-diagonal 142 px) shifted by up to 38 px = 24 m stays inside).
    """
    if len(seq) == 0:
        raise ConfigError(f"sequence {seq.name} at {seq.root} has no scans")
    big = CartesianConfig(width_px + 2 * margin_px, resolution_m)
    folder = cache_dir("training", "cartesian", _cache_key(seq, big))
    img_path, pose_path = folder / "images.npy", folder / "poses.npy"
    source = folder / CACHE_SOURCE_FILE  # `reradar cache --prune` drops folders whose sequence is gone
    if not source.is_file():
        source.write_text(json.dumps({"root": str(Path(seq.root).resolve())}))
    if not (img_path.is_file() and pose_path.is_file()):
        # Process-unique temporary names + atomic renames: two trainers started together may render the same
        # sequence; each finishes its own copy and the last rename wins (identical content). Poses land first
        # so that a visible images.npy always has its poses.
        tag = f"{os.getpid()}.tmp"
        tmp_poses = folder / f"poses.{tag}.npy"
        np.save(tmp_poses, np.asarray(seq.poses.poses, dtype=np.float64))
        tmp_poses.replace(pose_path)
        tmp = folder / f"images.{tag}.npy"
        arr = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.float16,
                                        shape=(len(seq), big.width_px, big.width_px))
        for i in tqdm(range(len(seq)), desc=f"cartesian {seq.name}", disable=not progress, leave=False):
            arr[i] = polar_to_cartesian(seq.load_scan(i), big)
        arr.flush()
        del arr
        tmp.replace(img_path)
    images = np.load(img_path, mmap_mode="r")
    poses = np.load(pose_path)
    return CachedSequence(str(seq.name), group or sequence_group(seq), images, poses, resolution_m)


def crop_view(big: np.ndarray, width_px: int, resolution_m: float, T_orig_new: np.ndarray) -> np.ndarray:
    """Render the image a sensor at ``T_orig_new`` (x, y [m], yaw [rad] in the original sensor frame) would
    see, from an oversized Cartesian image centred on the original sensor.

    Output pixel (i, j) is the new-frame point p' = ((c - i) r, (c - j) r); it is sampled at
    p = R(yaw) p' + t in the original frame (bilinear). Returns (W, W) float32.
    """
    x, y, yaw = (float(v) for v in T_orig_new)
    s = big.shape[0]
    cb, co, r = (s - 1) / 2.0, (width_px - 1) / 2.0, resolution_m
    ca, sa = np.cos(yaw), np.sin(yaw)
    # big-image (row, col) = (cb - p_x / r, cb - p_y / r) with p = R p' + t and p' = ((co - i) r, (co - j) r)
    # -> row = cb - ca (co - i) + sa (co - j) - x / r ; col = cb - sa (co - i) - ca (co - j) - y / r
    # cv2 maps output (u=col=j, v=row=i) -> source (col, row) with WARP_INVERSE_MAP.
    m = np.array([
        [ca, sa, cb - sa * co - ca * co - y / r],   # source col as a function of (j, i)
        [-sa, ca, cb - ca * co + sa * co - x / r],  # source row
    ], dtype=np.float64)
    img = np.asarray(big, dtype=np.float32)
    return cv2.warpAffine(img, m, (width_px, width_px), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)


class TrainingSet:
    """All training scans: (sequence index, scan index) items with world positions and place groups."""

    def __init__(self, sequences: list[CachedSequence]) -> None:
        if not sequences:
            raise ConfigError("no training sequences given")
        self.sequences = sequences
        self.seq_index = np.concatenate([np.full(len(s), i) for i, s in enumerate(sequences)])
        self.scan_index = np.concatenate([np.arange(len(s)) for s in sequences])
        self.xy = np.concatenate([s.poses[:, :2] for s in sequences]).astype(np.float64)
        groups = sorted({s.group for s in sequences})
        gid = {g: i for i, g in enumerate(groups)}
        self.group = np.concatenate([np.full(len(s), gid[s.group]) for s in sequences])
        self.groups = groups

    def __len__(self) -> int:
        return len(self.xy)

    def image(self, item: int) -> np.ndarray:
        return self.sequences[self.seq_index[item]].images[self.scan_index[item]]

    def view(self, item: int, width_px: int, T_orig_new: np.ndarray) -> np.ndarray:
        seq = self.sequences[self.seq_index[item]]
        return crop_view(seq.images[self.scan_index[item]], width_px, seq.resolution_m, T_orig_new)


class TupleSampler:
    """Batches of (anchor, positive) pairs whose anchors are far apart, for InfoNCE with in-batch negatives.

    Positive: same group, world distance <= ``pos_radius_m`` (a revisit — another sequence or > 40 frames
    apart — preferred with probability ``prefer_other_sequence``; never the anchor itself). Anchors of one batch are pairwise farther than ``neg_radius_m + pos_radius_m`` apart (or in
    different groups), so every other image of the batch — the other anchors and their positives — is
    farther than ``neg_radius_m`` from each anchor: with ``batch_pairs = num_negatives / 2 + 1`` (8 for the
    paper's 14 negatives) each anchor gets exactly ``num_negatives`` in-batch negatives. With ``same_group``
    the anchors come from one place group whenever it has room for them, so negatives are other places of the
    same world and weather, not other worlds.
    """

    def __init__(self, data: TrainingSet, pos_radius_m: float = 10.0, neg_radius_m: float = 25.0,
                 batch_pairs: int = 8, prefer_other_sequence: float = 0.75, same_group: bool = True) -> None:
        if not (0 < pos_radius_m < neg_radius_m):
            raise ConfigError(f"need 0 < pos_radius ({pos_radius_m}) < neg_radius ({neg_radius_m})")
        if batch_pairs < 2:
            raise ConfigError(f"batch_pairs must be >= 2, got {batch_pairs}")
        from scipy.spatial import cKDTree

        self.data, self.pos_r, self.neg_r = data, pos_radius_m, neg_radius_m
        self.batch_pairs, self.prefer_other, self.same_group = batch_pairs, prefer_other_sequence, same_group
        self.positives: list[np.ndarray] = [np.zeros(0, np.int64)] * len(data)
        for g in range(len(data.groups)):
            idx = np.flatnonzero(data.group == g)
            tree = cKDTree(data.xy[idx])
            for local, nb in enumerate(tree.query_ball_point(data.xy[idx], pos_radius_m)):
                cand = idx[np.asarray(nb, dtype=np.int64)]
                self.positives[idx[local]] = cand[cand != idx[local]]
        self.anchors = np.array([i for i in range(len(data)) if len(self.positives[i]) > 0], dtype=np.int64)
        if len(self.anchors) == 0:
            raise ConfigError(f"no scan has a positive within {pos_radius_m} m; scans are too sparse")

    def sample(self, rng: np.random.Generator, bank: np.ndarray | None = None, hard_pairs: int = 0,
               hard_pool: int = 10) -> tuple[np.ndarray, np.ndarray]:
        """(batch_pairs,) anchor items and (batch_pairs,) positive items (may be fewer if the data is small).

        Hard negatives (``bank``: (N, D) L2-normalised global descriptors of every training item, e.g. a
        memory bank refreshed every K steps; ``hard_pairs`` > 0): after the first, random anchor, the next
        ``hard_pairs`` anchors are mined — each is drawn uniformly from the ``hard_pool`` candidates whose bank
        descriptor is nearest to that of a randomly chosen anchor already in the batch, among candidates of
        the first anchor's place group that are farther than ``neg_radius_m + pos_radius_m`` from every
        chosen anchor (so they and their positives are true negatives). The remaining anchors are random as
        without a bank. Since every image's negatives are the other pairs of the batch, each mined pair adds
        two hard negatives for the anchor it was mined against (classic NetVLAD / PointNetVLAD mining).
        """
        d = self.data
        min_sep = self.neg_r + self.pos_r
        anchors: list[int] = []
        order = rng.permutation(self.anchors)
        if self.same_group:
            # all anchors from one place group first (the group of a random anchor, so groups are drawn in
            # proportion to their size): negatives from other worlds / weather could be told apart by their
            # global appearance alone, a shortcut that does not teach place recognition.
            g = d.group[order[0]]
            order = np.concatenate([order[d.group[order] == g], order[d.group[order] != g]])
        if bank is not None and hard_pairs > 0:
            anchors.append(int(order[0]))
            cand_all = self.anchors[d.group[self.anchors] == d.group[order[0]]]
            for _ in range(min(hard_pairs, self.batch_pairs - 1)):
                dist = np.min(np.hypot(*(d.xy[cand_all][:, None, :] - d.xy[anchors][None, :, :]).transpose(2, 0, 1)),
                              axis=1)
                cand = cand_all[dist > min_sep]
                if len(cand) == 0:
                    break
                q = anchors[int(rng.integers(len(anchors)))]
                sim = bank[cand] @ bank[q]
                k = min(hard_pool, len(cand))
                top = np.argpartition(-sim, k - 1)[:k]
                top = top[np.lexsort((cand[top], -sim[top]))]  # deterministic order (ties by item index)
                anchors.append(int(cand[top[int(rng.integers(k))]]))
        for a in order:
            if int(a) in anchors:
                continue
            if len(anchors) >= self.batch_pairs:
                break
            same = [b for b in anchors if d.group[b] == d.group[a]]
            if same and np.min(np.hypot(*(d.xy[same] - d.xy[a]).T)) <= min_sep:
                continue
            anchors.append(int(a))
            if len(anchors) == self.batch_pairs:
                break
        positives = []
        for a in anchors:
            cand = self.positives[a]
            # prefer a revisit (another sequence, or the same sequence much later) over the next frame
            other = cand[(d.seq_index[cand] != d.seq_index[a]) | (np.abs(d.scan_index[cand] - d.scan_index[a]) > 40)]
            if len(other) and rng.random() < self.prefer_other:
                cand = other
            positives.append(int(rng.choice(cand)))
        return np.asarray(anchors, np.int64), np.asarray(positives, np.int64)
