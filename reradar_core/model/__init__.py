"""The learned descriptor: C8 ReResNet (e2cnn) -> group pooling -> F' -> NetVLAD -> PCA-whitening.

Inference uses the exported plain-torch network (``DescriptorNet``) through ``DescriptorExtractor``;
training builds the e2cnn network (``reradar_core.model.equivariant``, imported lazily because e2cnn is slow to
import and only training needs it).
"""

from reradar_core.model.config import BACKBONES, ModelConfig
from reradar_core.model.extractor import DEFAULT_MAX_KEYPOINTS, DescriptorExtractor, sample_feature_map
from reradar_core.model.network import DescriptorNet, NetVLAD, PlainBackbone, group_max_pool
from reradar_core.model.registry import DEFAULT_MODEL, WEIGHTS_DIR, available_models, save_weights

__all__ = [
    "BACKBONES",
    "DEFAULT_MAX_KEYPOINTS",
    "DEFAULT_MODEL",
    "DescriptorExtractor",
    "DescriptorNet",
    "ModelConfig",
    "NetVLAD",
    "PlainBackbone",
    "WEIGHTS_DIR",
    "available_models",
    "group_max_pool",
    "sample_feature_map",
    "save_weights",
]
