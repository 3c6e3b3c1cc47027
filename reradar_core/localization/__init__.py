"""Localization stage: one ``Localizer`` (retrieval -> landmark-alignment screen -> guided pose -> re-ranking)
over a map's keyframes (``KeyframeSource``), with a tracking mode from a pose prior (``Localizer.track``);
``localize`` is the screen/verify step over given candidates."""

from reradar_core.localization.confidence import ConfidenceCues, ConfidenceModel, default_confidence_model
from reradar_core.localization.extractor import FeatureExtractor, load_default_extractor
from reradar_core.localization.far_view import FarViewConfig, TwoViewResult, localize_two_views
from reradar_core.localization.keyframes import (
    CachedKeyframe,
    InMemoryKeyframes,
    KeyframeCache,
    KeyframeSource,
)
from reradar_core.localization.localizer import Localizer, Retrieval
from reradar_core.localization.pipeline import (
    REASON_AMBIGUOUS,
    REASON_INCONSISTENT,
    REASON_LOW_CONFIDENCE,
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
from reradar_core.localization.repetition import PlaceRepetition, RepetitionTable, repetition_settings
from reradar_core.localization.tracking import PosePrior, TrackingConfig

__all__ = [
    "FarViewConfig",
    "TwoViewResult",
    "localize_two_views",
    "ConfidenceCues",
    "ConfidenceModel",
    "default_confidence_model",
    "REASON_LOW_CONFIDENCE",
    "FeatureExtractor",
    "load_default_extractor",
    "CachedKeyframe",
    "InMemoryKeyframes",
    "KeyframeCache",
    "KeyframeSource",
    "Localizer",
    "Retrieval",
    "PlaceRepetition",
    "RepetitionTable",
    "repetition_settings",
    "PosePrior",
    "TrackingConfig",
    "REASON_INCONSISTENT",
    "REASON_NO_CANDIDATE",
    "REASON_AMBIGUOUS",
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
