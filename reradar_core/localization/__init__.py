"""Localization stage: one ``Localizer`` (retrieval -> landmark-alignment screen -> guided pose -> re-ranking)
over a map's keyframes (``KeyframeSource``); ``localize`` is the screen/verify step over given candidates."""

from reradar_core.localization.extractor import FeatureExtractor, load_default_extractor
from reradar_core.localization.keyframes import (
    CachedKeyframe,
    InMemoryKeyframes,
    KeyframeCache,
    KeyframeSource,
)
from reradar_core.localization.localizer import Localizer, Retrieval
from reradar_core.localization.pipeline import (
    REASON_NO_CANDIDATE,
    REASON_SCREENED_OUT,
    REASON_TOO_FEW_INLIERS,
    REASON_TOO_FEW_MATCHES,
    Candidate,
    CandidateVerification,
    LocalizationConfig,
    LocalizationResult,
    localize,
    verify_candidate,
)

__all__ = [
    "FeatureExtractor",
    "load_default_extractor",
    "CachedKeyframe",
    "InMemoryKeyframes",
    "KeyframeCache",
    "KeyframeSource",
    "Localizer",
    "Retrieval",
    "REASON_NO_CANDIDATE",
    "REASON_SCREENED_OUT",
    "REASON_TOO_FEW_INLIERS",
    "REASON_TOO_FEW_MATCHES",
    "Candidate",
    "CandidateVerification",
    "LocalizationConfig",
    "LocalizationResult",
    "localize",
    "verify_candidate",
]
