"""Evaluation metrics of the paper: Recall@1, F1max, localization success rate and pose errors."""

from reradar_core.evaluation.metrics import (
    MAX_ROTATION_ERROR_DEG,
    RADIUS_M,
    LocalizationMetrics,
    PrecisionRecall,
    f1_max,
    has_revisit,
    localization_errors,
    localization_success,
    precision_recall_curve,
    radius_for,
    recall_at_1,
    retrieval_correct,
    rotation_success,
    rotation_success_rate,
    success_rate,
    summarize,
)

__all__ = [
    "MAX_ROTATION_ERROR_DEG",
    "RADIUS_M",
    "LocalizationMetrics",
    "PrecisionRecall",
    "f1_max",
    "has_revisit",
    "localization_errors",
    "localization_success",
    "precision_recall_curve",
    "radius_for",
    "recall_at_1",
    "retrieval_correct",
    "rotation_success",
    "rotation_success_rate",
    "success_rate",
    "summarize",
]
