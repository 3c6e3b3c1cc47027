"""InfoNCE training of the descriptor network (paper, Sec. "Network Training").

Recipe: L2-normalised global descriptors, InfoNCE with tau = 0.1, one positive within ``pos_radius_m`` and
14 negatives outside ``neg_radius_m`` (in-batch: 8 far-apart anchor/positive pairs per batch), random-yaw and
small translation augmentation, AdamW with lr 1e-4 from scratch and 1e-5 when adapting a trained model. The
NetVLAD centres are initialised by k-means on F' features and the projection by PCA-whitening of raw NetVLAD
vectors, then everything trains end to end. Checkpoints (model, optimizer, step, history) resume exactly:
the batch of step s is drawn from ``default_rng([seed, s])``.
"""

from __future__ import annotations

import hashlib
import logging
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from reradar_core.errors import ConfigError, ModelMismatchError, ReRadarError
from reradar_core.model.config import ModelConfig
from reradar_core.model.network import DescriptorNet
from reradar_core.training.data import CachedSequence, TrainingSet, TupleSampler
from reradar_core.training.loss import info_nce_in_batch

__all__ = ["TrainConfig", "Trainer", "TrainingDivergedError", "recall_at_1_from_descriptors", "trainable_state",
           "load_trainable_state", "RESUME_FREE_SETTINGS"]

logger = logging.getLogger(__name__)


class TrainingDivergedError(ReRadarError):
    """The loss became NaN or infinite (learning rate or a loss weight too large): no weights are written."""


@dataclass(frozen=True)
class TrainConfig:
    """Training hyper-parameters; defaults are the paper's where it gives them.

    Attributes:
        lr: AdamW learning rate (paper: 1e-4 from scratch, 1e-5 when adapting).
        tau: InfoNCE temperature (paper: 0.1). num_negatives: per query (paper: 14) -> num_negatives/2 + 1
            anchor/positive pairs per batch.
        pos_radius_m / neg_radius_m: positive within, negatives beyond (our defaults: 10 m / 25 m; the simulated sequences are sampled every 8-15 m, so 5 m would leave most scans without a positive).
        yaw_augment: random heading in [0, 2 pi) per image; trans_augment_m: uniform shift in [-t, t] m.
        max_steps / max_minutes: stop at whichever comes first.
        val_every / checkpoint_every: in steps. recall_radius_m: a retrieval is correct within this distance.
        device: ``auto`` (CUDA when available, else CPU), ``cpu`` or ``cuda``. On CUDA the same seed gives
            close but not bit-identical weights (cuDNN kernels are not deterministic).
        hard_negatives: how many of the ``num_negatives`` negatives of a query are mined from a memory bank
            instead of drawn at random (even; 0 = off, the default). The bank holds the global descriptors
            (centre crop, eval mode) of every training scan and is refreshed every ``hard_refresh_every``
            steps; ``hard_negatives / 2`` anchors of each batch are drawn from the ``hard_pool`` nearest bank
            descriptors of an anchor already in the batch, among places farther than ``neg_radius_m +
            pos_radius_m`` (``TupleSampler.sample``). The bank is saved in checkpoints, so resuming stays exact.
        learned_whitening: after the last step, replace the projection by learned whitening of the raw NetVLAD
            vectors of the training scans (``training.whitening``): matching pairs are each scan with its
            nearest scan of another traversal within ``pos_radius_m``, plus, with ``whitening_rotation_pairs``,
            each scan with a copy turned by a random heading (seeded). ``whitening_shrinkage``: see
            ``learned_whitening``. Off by default (the paper trains the projection end to end); the shipped
            stage-2 models use it (docs/MODEL.md, "Learned whitening").
        rotation_consistency: weight of a rotation-consistency term (0 = off, the default): each batch also holds
            a copy of every anchor view turned by another random heading about the sensor (same shift), and the
            loss adds ``rotation_consistency * mean(1 - cos(g(anchor), g(turned copy)))`` on the global
            descriptors, pushing the descriptor towards invariance at any angle, not only at the C8 group's
            exact 90-degree steps (issue 11; docs/MODEL.md, "Rotation consistency").
        num_threads: torch CPU threads. Default 1: on the shared 2-core machine two threads ran 3-6x slower
            per step than one whenever other processes competed for the cores (OpenMP threads waiting on
            each other), while on an idle machine two threads gain only ~1.6x.
    """

    model: ModelConfig = field(default_factory=ModelConfig)
    lr: float = 1e-4
    weight_decay: float = 1e-4
    tau: float = 0.1
    num_negatives: int = 14
    pos_radius_m: float = 10.0
    neg_radius_m: float = 25.0
    yaw_augment: bool = True
    trans_augment_m: float = 2.0
    max_steps: int = 1500
    max_minutes: float = 60.0
    val_every: int = 100
    checkpoint_every: int = 25
    recall_radius_m: float = 25.0
    val_max_database: int = 200
    val_max_queries: int = 100
    kmeans_images: int = 48
    whiten_images: int = 192
    hard_negatives: int = 0
    hard_refresh_every: int = 100
    hard_pool: int = 10
    learned_whitening: bool = False
    whitening_shrinkage: float = 0.1
    whitening_rotation_pairs: bool = True
    rotation_consistency: float = 0.0
    seed: int = 0
    num_threads: int = 1
    device: str = "auto"

    def __post_init__(self) -> None:
        if self.hard_negatives < 0 or self.hard_negatives % 2 or self.hard_negatives > self.num_negatives:
            raise ConfigError(f"hard_negatives must be even and in [0, num_negatives={self.num_negatives}] "
                              f"(each mined anchor/positive pair gives two negatives), got {self.hard_negatives}")
        if self.hard_refresh_every < 1 or self.hard_pool < 1:
            raise ConfigError("hard_refresh_every and hard_pool must be >= 1")
        if not (math.isfinite(self.rotation_consistency) and self.rotation_consistency >= 0):
            raise ConfigError(f"rotation_consistency must be a finite weight >= 0, got {self.rotation_consistency}")

    @property
    def batch_pairs(self) -> int:
        return self.num_negatives // 2 + 1

    @property
    def hard_pairs(self) -> int:
        return self.hard_negatives // 2

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["model"] = self.model.to_dict()
        return d


_BASIS_KEYS = ("sampled_basis", ".filter", "expanded_bias")

#: ``TrainConfig`` fields that may differ between a checkpoint and the run that resumes it, because they provably
#: do not change the weights: the stopping rule (``max_steps`` may only grow past the checkpoint's step: the batch
#: of step s depends on (seed, s) alone and the learning rate has no schedule), validation and checkpointing
#: (no-grad, eval mode) and the learned whitening (fitted after the last step; checkpoints keep the trained
#: projection). Every other field, the resolved device, the --init weights and the training data must match.
RESUME_FREE_SETTINGS = frozenset({"max_steps", "max_minutes", "val_every", "checkpoint_every", "recall_radius_m",
                                  "val_max_database", "val_max_queries", "learned_whitening",
                                  "whitening_shrinkage", "whitening_rotation_pairs", "device", "model"})

#: settings left out of ``Trainer.settings`` at their default (so checkpoints written before them stay resumable)
_UNRECORDED_DEFAULTS = {"rotation_consistency": 0.0}

#: how the resume check names a setting (the ``reradar train`` option where there is one)
_SETTING_NAMES = {"lr": "--lr", "seed": "--seed", "num_threads": "--threads", "device_type": "--device",
                  "hard_negatives": "--hard-negatives", "hard_refresh_every": "--hard-refresh",
                  "rotation_consistency": "--rotation-consistency",
                  "init": "--init weights", "data": "training data (--split / --sequence)"}


def _tensors_sha256(state: dict[str, torch.Tensor]) -> str:
    h = hashlib.sha256()
    for k in sorted(state):
        t = state[k].detach().cpu().contiguous()
        h.update(k.encode())
        h.update(str(t.dtype).encode())
        h.update(str(tuple(t.shape)).encode())
        h.update(t.numpy().tobytes() if t.dtype != torch.bfloat16 else t.float().numpy().tobytes())
    return h.hexdigest()


def _data_fingerprint(seqs: list[CachedSequence]) -> str:
    """Cheap identity of the training data: each sequence's name, group, length, poses and image shape, plus
    eight evenly spaced images (hashing every image would read hundreds of MB)."""
    h = hashlib.sha256()
    for seq in seqs:
        h.update(f"{seq.name}|{seq.group}|{len(seq)}|{tuple(seq.images.shape)}|{seq.images.dtype}|"
                 f"{seq.resolution_m}".encode())
        h.update(np.ascontiguousarray(np.asarray(seq.poses, np.float64)).tobytes())
        for i in np.unique(np.linspace(0, len(seq.images) - 1, 8).round().astype(int)) if len(seq.images) else []:
            h.update(np.ascontiguousarray(np.asarray(seq.images[int(i)])).tobytes())
    return h.hexdigest()


def trainable_state(net: torch.nn.Module) -> dict[str, torch.Tensor]:
    """State dict without e2cnn's derived buffers (sampled bases, expanded filters): small and sufficient."""
    return {k: v.detach().cpu().clone() for k, v in net.state_dict().items()
            if not any(s in k for s in _BASIS_KEYS)}


def load_trainable_state(net: torch.nn.Module, state: dict[str, torch.Tensor]) -> None:
    """Load a ``trainable_state`` dict; only derived buffers may be missing."""
    missing, unexpected = net.load_state_dict(state, strict=False)
    bad = [k for k in missing if not any(s in k for s in _BASIS_KEYS)]
    if bad or unexpected:
        raise ModelMismatchError(f"training state does not fit the network: missing {bad[:5]}, "
                                 f"unexpected {list(unexpected)[:5]}")
    mode = net.training
    net.train(True)  # e2cnn recomputes its cached expanded filters on the next switch to eval mode
    net.train(mode)


def resolve_device(name: str) -> torch.device:
    """``auto`` -> CUDA when available else CPU; ``cpu``; ``cuda`` (ConfigError when CUDA is missing)."""
    key = name.strip().lower()
    if key == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if key == "cpu":
        return torch.device("cpu")
    if key.startswith("cuda"):
        if not torch.cuda.is_available():
            raise ConfigError(f"device {name!r} requested but this torch build sees no CUDA GPU "
                              f"(torch {torch.__version__}); use --device cpu or auto")
        return torch.device(key)
    raise ConfigError(f"unknown device {name!r}; choose auto, cpu or cuda")


def recall_at_1_from_descriptors(db_desc: np.ndarray, db_xy: np.ndarray, q_desc: np.ndarray,
                                 q_xy: np.ndarray, radius_m: float) -> tuple[float, int]:
    """Recall@1 (fraction, #evaluated queries) by inner product; queries with no database scan within
    ``radius_m`` are not evaluated."""
    d = np.hypot(q_xy[:, None, 0] - db_xy[None, :, 0], q_xy[:, None, 1] - db_xy[None, :, 1])
    valid = d.min(axis=1) <= radius_m
    if not valid.any():
        return float("nan"), 0
    top = np.argmax(q_desc @ db_desc.T, axis=1)
    hit = d[np.arange(len(q_xy)), top] <= radius_m
    return float(hit[valid].mean()), int(valid.sum())


def _subsample(n: int, k: int) -> np.ndarray:
    return np.arange(n) if n <= k else np.unique(np.linspace(0, n - 1, k).round().astype(int))


class Trainer:
    """Trains one network on cached sequences; ``run()`` returns the exported plain network and a summary."""

    def __init__(self, config: TrainConfig, train: list[CachedSequence],
                 val_pairs: list[tuple[CachedSequence, CachedSequence]] | None = None,
                 run_dir: str | Path | None = None, init_state: dict[str, torch.Tensor] | None = None,
                 progress: bool = True) -> None:
        from reradar_core.model.equivariant import build_training_net

        self.config = config
        torch.manual_seed(config.seed)
        torch.set_num_threads(max(1, config.num_threads))
        self.data = TrainingSet(train)
        self.sampler = TupleSampler(self.data, config.pos_radius_m, config.neg_radius_m, config.batch_pairs)
        self.val_pairs = val_pairs or []
        self._check_validation_overlap()
        self.run_dir = Path(run_dir) if run_dir is not None else None
        self.progress = progress
        self.device = resolve_device(config.device)
        self.net: DescriptorNet = build_training_net(config.model)
        self.adapted = init_state is not None
        if init_state is not None:
            load_trainable_state(self.net, init_state)
        self.net.to(self.device)
        self.opt = torch.optim.AdamW(self.net.parameters(), lr=config.lr, weight_decay=config.weight_decay)
        self.step = 0
        self.elapsed_s = 0.0
        self.history: list[dict[str, Any]] = []
        self.initialised = self.adapted
        self.bank: np.ndarray | None = None  # memory bank of global descriptors (hard negatives)
        self.bank_step = -1
        self.last_loss: float | None = None  # mean loss of the last steps, kept across resumes
        self.checkpoint_step: int | None = None  # step of the last checkpoint written or resumed
        # what determines the weights besides the step count: checked when a checkpoint is resumed
        cfg = config.to_dict()
        self.settings: dict[str, Any] = {k: v for k, v in cfg.items() if k not in RESUME_FREE_SETTINGS}
        for key, default in _UNRECORDED_DEFAULTS.items():
            if self.settings.get(key) == default:  # what checkpoints written before the option did: still resumable
                del self.settings[key]
        self.settings.update(device_type=self.device.type, data=_data_fingerprint(self.data.sequences),
                             init=None if init_state is None else _tensors_sha256(init_state))

    def _check_validation_overlap(self) -> None:
        """Refuse validation data with no query within ``recall_radius_m`` of a database scan (drives that do not
        overlap, or poses in different frames): its Recall@1 would be NaN over 0 queries. One pair without overlap
        among others is only logged (a reversed drive's tail can lie away from the map's)."""
        c = self.config
        counted = 0
        for db, q in self.val_pairs:
            dxy = np.asarray(db.poses, np.float64)[_subsample(len(db), c.val_max_database), :2]
            qxy = np.asarray(q.poses, np.float64)[_subsample(len(q), c.val_max_queries), :2]
            near = int((np.hypot(qxy[:, None, 0] - dxy[None, :, 0], qxy[:, None, 1] - dxy[None, :, 1]).min(axis=1)
                        <= c.recall_radius_m).sum()) if len(dxy) and len(qxy) else 0
            if near == 0:
                logger.warning("validation pair %s / %s: no query within %g m of a database scan", db.name, q.name,
                               c.recall_radius_m)
            counted += near
        if self.val_pairs and counted == 0:
            names = "; ".join(f"{db.name} / {q.name}" for db, q in self.val_pairs)
            raise ConfigError(f"validation ({names}): no query lies within {c.recall_radius_m:g} m of a database "
                              "scan, so there is nothing to validate: the drives do not overlap, or their poses are "
                              "in different frames")

    # ------------------------------------------------------------------ batches
    def _view_transforms(self, n: int, rng: np.random.Generator, augment: bool = True) -> np.ndarray:
        """(n, 3) T_orig_new (x, y metres, yaw radians) of n random views: shift in +-trans_augment_m, any
        heading (drawn item by item, shift then heading: the order every shipped model was trained with)."""
        c = self.config
        out = np.zeros((n, 3))
        if not augment:
            return out
        for k in range(n):
            t = rng.uniform(-c.trans_augment_m, c.trans_augment_m, 2) if c.trans_augment_m > 0 else (0, 0)
            yaw = rng.uniform(0, 2 * math.pi) if c.yaw_augment else 0.0
            out[k] = (t[0], t[1], yaw)
        return out

    def _render_views(self, items: np.ndarray, T: np.ndarray) -> torch.Tensor:
        """(len(items), 1, W, W) float32 views of training scans, item k seen from ``T[k]``."""
        w = self.config.model.cartesian_width_px
        out = np.empty((len(items), 1, w, w), np.float32)
        for k, it in enumerate(items):
            out[k, 0] = self.data.view(int(it), w, T[k])
        return torch.from_numpy(out).to(self.device)

    def _views(self, items: np.ndarray, rng: np.random.Generator, augment: bool = True) -> torch.Tensor:
        return self._render_views(items, self._view_transforms(len(items), rng, augment))

    @torch.no_grad()
    def initialise_heads(self) -> None:
        """k-means NetVLAD centres on F' features, then PCA-whitening of raw NetVLAD vectors."""
        import faiss

        c = self.config
        rng = np.random.default_rng([c.seed, 10_000_019])
        self.net.train()  # batch statistics: BN running stats are still at their initial values
        items = rng.choice(len(self.data), size=min(c.kmeans_images, len(self.data)), replace=False)
        feats = []
        for chunk in np.array_split(items, max(1, len(items) // 16)):
            f = self.net.backbone(self.net.mask_input(self._views(chunk, rng)))
            f = torch.nn.functional.normalize(f, dim=1)
            feats.append(f.permute(0, 2, 3, 1).reshape(-1, f.shape[1]))
        x = torch.cat(feats).cpu().numpy().astype(np.float32)
        x = x[rng.choice(len(x), size=min(len(x), 50_000), replace=False)]
        km = faiss.Kmeans(x.shape[1], c.model.num_clusters, niter=25, seed=c.seed, verbose=False)
        km.train(np.ascontiguousarray(x))
        self.net.netvlad.init_from_centroids(torch.from_numpy(km.centroids).to(self.device))
        if self.net.proj is not None:
            items = rng.choice(len(self.data), size=min(c.whiten_images, len(self.data)), replace=False)
            vl = [self.net.vlad(self.net.backbone(self.net.mask_input(self._views(ch, rng))))
                  for ch in np.array_split(items, max(1, len(items) // 16))]
            self.net.init_whitening(torch.cat(vl))
        self.initialised = True

    @torch.no_grad()
    def refresh_bank(self) -> None:
        """Global descriptors (eval mode, centre crop, no augmentation) of every training scan."""
        c = self.config
        w = c.model.cartesian_width_px
        was = self.net.training
        self.net.eval()
        out = []
        for seq in self.data.sequences:
            for chunk in np.array_split(np.arange(len(seq)), max(1, math.ceil(len(seq) / 32))):
                s = seq.images.shape[1]
                o = (s - w) // 2
                x = torch.from_numpy(np.asarray(seq.images[chunk, o:o + w, o:o + w], np.float32))[:, None]
                g, _ = self.net(x.to(self.device))
                out.append(g.cpu().numpy())
        self.net.train(was)
        self.bank = np.ascontiguousarray(np.concatenate(out).astype(np.float32))
        self.bank_step = self.step

    @torch.no_grad()
    def raw_vlad(self, items: np.ndarray, yaw_rad: np.ndarray | None = None) -> np.ndarray:
        """(len(items), K*C) float64 raw NetVLAD vectors (eval mode) of training scans: centre crops, or views
        turned by ``yaw_rad`` (one heading per item, radians) about the sensor."""
        w = self.config.model.cartesian_width_px
        was = self.net.training
        self.net.eval()
        out = []
        for chunk in np.array_split(np.arange(len(items)), max(1, math.ceil(len(items) / 32))):
            imgs = np.stack([self.data.view(int(items[k]), w, np.array([0.0, 0.0, 0.0 if yaw_rad is None
                                                                       else float(yaw_rad[k])]))
                             for k in chunk]).astype(np.float32)
            x = torch.from_numpy(imgs)[:, None].to(self.device)
            out.append(self.net.vlad(self.net.backbone(self.net.mask_input(x))).double().cpu().numpy())
        self.net.train(was)
        return np.concatenate(out)

    @torch.no_grad()
    def fit_learned_whitening(self) -> dict[str, Any]:
        """Replace the projection by learned whitening (``TrainConfig.learned_whitening``); returns a summary."""
        from reradar_core.training.whitening import learned_whitening, matching_pairs

        c = self.config
        if self.net.proj is None:
            raise ConfigError("learned whitening needs a projection (output_dim); this model has none")
        items = np.arange(len(self.data))
        raw = self.raw_vlad(items)
        pairs = matching_pairs(self.data.xy, self.data.seq_index, self.data.group, c.pos_radius_m)
        a, b = raw[pairs[:, 0]], raw[pairs[:, 1]]
        summary: dict[str, Any] = {"scans": int(len(items)), "traversal_pairs": int(len(pairs)),
                                   "rotation_pairs": 0, "shrinkage": c.whitening_shrinkage}
        if c.whitening_rotation_pairs:
            rng = np.random.default_rng([c.seed, 20_000_003])
            turned = self.raw_vlad(items, rng.uniform(0.0, 2 * math.pi, len(items)))
            a, b = np.concatenate([a, raw]), np.concatenate([b, turned])
            summary["rotation_pairs"] = int(len(items))
        weight, bias = learned_whitening(a, b, raw, self.net.proj.out_features, c.whitening_shrinkage)
        self.net.proj.weight.copy_(torch.from_numpy(weight).float())
        self.net.proj.bias.copy_(torch.from_numpy(bias).float())
        logger.info("learned whitening: %s", summary)
        return summary

    # ------------------------------------------------------------------ validation
    @torch.no_grad()
    def validate(self) -> dict[str, float]:
        """Recall@1 on the validation pairs, with the projection ("r1") and on raw NetVLAD ("r1_raw")."""
        if not self.val_pairs:
            return {}
        c = self.config
        was = self.net.training
        self.net.eval()
        hits, hits_raw, total = 0.0, 0.0, 0
        w = c.model.cartesian_width_px
        for db, q in self.val_pairs:
            res = []
            for seq, cap in ((db, c.val_max_database), (q, c.val_max_queries)):
                idx = _subsample(len(seq), cap)
                g_all, v_all = [], []
                for chunk in np.array_split(idx, max(1, math.ceil(len(idx) / 32))):
                    s = seq.images.shape[1]
                    o = (s - w) // 2
                    x = torch.from_numpy(np.asarray(seq.images[chunk, o:o + w, o:o + w], np.float32))[:, None]
                    x = x.to(self.device)
                    fmap = self.net.backbone(self.net.mask_input(x))
                    v = self.net.vlad(fmap)
                    g = torch.nn.functional.normalize(self.net.proj(v), dim=1) if self.net.proj is not None else v
                    g_all.append(g.cpu().numpy())
                    v_all.append(v.cpu().numpy())
                res.append((np.concatenate(g_all), np.concatenate(v_all), seq.poses[idx, :2]))
            (gd, vd, xd), (gq, vq, xq) = res
            r, n = recall_at_1_from_descriptors(gd, xd, gq, xq, c.recall_radius_m)
            rr, _ = recall_at_1_from_descriptors(vd, xd, vq, xq, c.recall_radius_m)
            if n:
                hits += r * n
                hits_raw += rr * n
                total += n
        self.net.train(was)
        if total == 0:
            return {"r1": float("nan"), "r1_raw": float("nan"), "val_queries": 0}
        return {"r1": hits / total, "r1_raw": hits_raw / total, "val_queries": total}

    # ------------------------------------------------------------------ checkpoints
    @property
    def checkpoint_path(self) -> Path | None:
        return self.run_dir / "checkpoint.pt" if self.run_dir is not None else None

    def save_checkpoint(self) -> None:
        path = self.checkpoint_path
        if path is None:
            return
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        torch.save({"net": trainable_state(self.net), "opt": self.opt.state_dict(), "step": self.step,
                    "elapsed_s": self.elapsed_s, "history": self.history, "initialised": self.initialised,
                    "config": self.config.to_dict(), "settings": self.settings, "last_loss": self.last_loss,
                    "bank": None if self.bank is None else torch.from_numpy(self.bank), "bank_step": self.bank_step},
                   tmp)
        tmp.replace(path)
        self.checkpoint_step = self.step

    def load_checkpoint(self) -> bool:
        path = self.checkpoint_path
        if path is None or not path.is_file():
            return False
        ck = torch.load(path, map_location="cpu", weights_only=False)
        saved = ck.get("config", {}).get("model")
        # options added later (e.g. disc_mask) take their defaults in checkpoints written before them
        if saved is None or ModelConfig.from_dict(saved).to_dict() != self.config.model.to_dict():
            raise ConfigError(f"checkpoint {path} was written for another model config; pass --no-resume to start over, or use another --name")
        self._check_resumable(path, ck)
        load_trainable_state(self.net, ck["net"])
        self.opt.load_state_dict(ck["opt"])
        self.step, self.elapsed_s = int(ck["step"]), float(ck["elapsed_s"])
        self.history, self.initialised = list(ck["history"]), bool(ck["initialised"])
        bank = ck.get("bank")
        self.bank = None if bank is None else bank.numpy()
        self.bank_step = int(ck.get("bank_step", -1))
        self.last_loss = ck.get("last_loss")
        self.checkpoint_step = self.step
        logger.info("resumed %s at step %d", path, self.step)
        return True

    def _check_resumable(self, path: Path, ck: dict[str, Any]) -> None:
        """Refuse a checkpoint that would not give this run's weights: other settings (``self.settings``), none
        recorded (written before they were), or a step past ``max_steps``."""
        advice = "pass --no-resume to start over, or use another --name"
        saved = ck.get("settings")
        if not isinstance(saved, dict):
            raise ConfigError(f"checkpoint {path} records no training settings (written by an older version), so "
                              f"resuming it cannot be checked to give this command's weights; {advice}")
        diff = []
        for key in sorted(set(saved) | set(self.settings)):
            default = _UNRECORDED_DEFAULTS.get(key, "<not recorded>")  # left out when off: see ``__init__``
            old, new = saved.get(key, default), self.settings.get(key, default)
            if old != new:
                if key in ("init", "data"):
                    old, new = (v[:12] if isinstance(v, str) else v for v in (old, new))
                diff.append(f"{_SETTING_NAMES.get(key, key)} {old} -> {new}")
        if diff:
            raise ConfigError(f"checkpoint {path} was written with other training settings ({'; '.join(diff)}): "
                              f"resuming it would not give this command's weights; {advice}")
        step = int(ck["step"])
        if step > self.config.max_steps:
            raise ConfigError(f"checkpoint {path} is at step {step}, past --steps {self.config.max_steps}: "
                              f"resuming it would not give this command's weights; {advice}")

    # ------------------------------------------------------------------ training
    def train_step(self) -> float:
        c = self.config
        rng = np.random.default_rng([c.seed, self.step])
        if c.hard_pairs > 0:
            if self.bank is None or (self.step % c.hard_refresh_every == 0 and self.bank_step != self.step):
                self.refresh_bank()
            anchors, positives = self.sampler.sample(rng, self.bank, c.hard_pairs, c.hard_pool)
        else:
            anchors, positives = self.sampler.sample(rng)
        items = np.concatenate([anchors, positives])
        T = self._view_transforms(len(items), rng)
        b = len(anchors)
        if c.rotation_consistency > 0:
            # each anchor once more, same shift, another heading (drawn after the batch's own views)
            turned = T[:b].copy()
            turned[:, 2] = rng.uniform(0, 2 * math.pi, b)
            items, T = np.concatenate([items, anchors]), np.concatenate([T, turned])
        x = self._render_views(items, T)
        self.net.train()
        g, _ = self.net(x)
        loss = info_nce_in_batch(g[:b], g[b:2 * b], tau=c.tau)
        if c.rotation_consistency > 0:
            loss = loss + c.rotation_consistency * (1.0 - (g[:b] * g[2 * b:]).sum(dim=1)).mean()
        if not torch.isfinite(loss):  # a diverged run: its weights would give NaN descriptors, never write them
            raise TrainingDivergedError(
                f"training diverged at step {self.step + 1}: the loss is {float(loss.detach())}; nothing was written. "
                f"Lower --lr (now {c.lr:g})" + (f" or --rotation-consistency (now {c.rotation_consistency:g})"
                                                if c.rotation_consistency > 0 else "") +
                ", and pass --no-resume to start over")
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        self.step += 1
        return float(loss.detach())

    def run(self, resume: bool = True) -> tuple[DescriptorNet, dict[str, Any]]:
        """Train until ``max_steps`` or ``max_minutes``; returns (exported plain net, summary dict)."""
        from reradar_core.model.equivariant import export_plain

        c = self.config
        if resume:
            self.load_checkpoint()
        if not self.initialised:
            self.initialise_heads()
        if self.step == 0 and self.val_pairs:
            v0 = self.validate()
            self.history.append({"step": 0, **v0})
            logger.info("initial validation: %s", v0)
        bar = tqdm(total=c.max_steps, initial=self.step, desc="train", disable=not self.progress, mininterval=5.0)
        losses: list[float] = []
        last_val = self.history[-1] if self.history else {}
        t0 = time.monotonic() - self.elapsed_s
        while self.step < c.max_steps and (time.monotonic() - t0) < c.max_minutes * 60:
            losses.append(self.train_step())
            self.elapsed_s = time.monotonic() - t0
            if self.val_pairs and self.step % c.val_every == 0:
                last_val = {"step": self.step, "loss": float(np.mean(losses[-c.val_every:])), **self.validate()}
                self.history.append(last_val)
                logger.info("step %d: %s", self.step, last_val)
            if self.step % c.checkpoint_every == 0:
                self.save_checkpoint()
            bar.update(1)
            bar.set_postfix(loss=f"{np.mean(losses[-20:]):.3f}", r1=f"{last_val.get('r1', float('nan')):.3f}")
        bar.close()
        if losses:
            self.last_loss = float(np.mean(losses[-50:]))
        whitening = None
        if c.learned_whitening:
            # the checkpoint keeps the trained projection: a resumed run fits the whitening again, never on top
            self.save_checkpoint()
            before = self.validate() if self.val_pairs else {}
            whitening = {**self.fit_learned_whitening(), "val_recall_at_1_before": before.get("r1")}
        final = self.validate() if self.val_pairs else {}
        # a resumed finished run re-validates (and re-fits the whitening): it replaces its final entry
        while self.history and self.history[-1].get("final") and self.history[-1].get("step") == self.step:
            self.history.pop()
        self.history.append({"step": self.step, "final": True, "loss": self.last_loss, **final})
        if whitening is None:
            self.save_checkpoint()
        summary = {"steps": self.step, "train_time_s": round(self.elapsed_s, 1),
                   "val_recall_at_1": final.get("r1"), "val_recall_at_1_raw_netvlad": final.get("r1_raw"),
                   "val_queries": final.get("val_queries"), "history": self.history,
                   "train_config": c.to_dict(), "adapted": self.adapted}
        if whitening is not None:
            summary["learned_whitening"] = whitening
        self.net.to("cpu")  # shipped weights and the e2cnn export live on the CPU
        return export_plain(self.net), summary
