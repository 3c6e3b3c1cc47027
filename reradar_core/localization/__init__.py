"""Global localization: top-k retrieval candidates -> landmark-alignment screen -> guided pose -> re-ranking."""

from reradar_core.localization.extractor import FeatureExtractor, load_default_extractor
from reradar_core.localization.pipeline import (
    REASON_NO_CANDIDATE,
    REASON_SCREENED_OUT,
    REASON_TOO_FEW_INLIERS,
    REASON_TOO_FEW_MATCHES,
    Candidate,
    CandidateVerification,
    KeyframeCandidates,
    LocalizationConfig,
    LocalizationResult,
    localize,
    verify_candidate,
)

__all__ = [
    "FeatureExtractor",
    "load_default_extractor",
    "REASON_NO_CANDIDATE",
    "REASON_SCREENED_OUT",
    "REASON_TOO_FEW_INLIERS",
    "REASON_TOO_FEW_MATCHES",
    "Candidate",
    "CandidateVerification",
    "KeyframeCandidates",
    "LocalizationConfig",
    "LocalizationResult",
    "localize",
    "verify_candidate",
]
