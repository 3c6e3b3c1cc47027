"""InfoNCE training of the descriptor network (paper, Sec. "Network Training"); ``reradar train``."""

from reradar_core.training.data import CachedSequence, TrainingSet, TupleSampler, cache_sequence, crop_view
from reradar_core.training.loss import info_nce, info_nce_in_batch
from reradar_core.training.trainer import TrainConfig, Trainer, recall_at_1_from_descriptors

__all__ = [
    "CachedSequence",
    "TrainConfig",
    "Trainer",
    "TrainingSet",
    "TupleSampler",
    "cache_sequence",
    "crop_view",
    "info_nce",
    "info_nce_in_batch",
    "recall_at_1_from_descriptors",
]
