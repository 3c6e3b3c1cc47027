"""The feature-extractor interface localization, map building and the service depend on.

``reradar_core.model.DescriptorExtractor`` implements it; tests inject small fakes where the network is not
what is being tested.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from reradar_core.features import ScanFeatures
from reradar_core.geometry.cartesian import CartesianConfig
from reradar_core.io.scan import RadarScan

__all__ = ["FeatureExtractor", "load_default_extractor"]


@runtime_checkable
class FeatureExtractor(Protocol):
    """Computes ``ScanFeatures`` for radar scans.

    Attributes:
        model_id: model identifier stored in maps.
        weights_sha256: SHA-256 of the weights; maps built with other weights are refused.
        descriptor_dim: global descriptor length D.
        cartesian: Cartesian image geometry the model uses.

    Extractors may also state ``local_dim`` (the local descriptor length C; ``DescriptorExtractor`` does): the
    service then refuses maps of another C (``MapRegistry.check_compatible``).
    """

    model_id: str
    weights_sha256: str
    descriptor_dim: int
    cartesian: CartesianConfig

    def describe(self, scan: RadarScan) -> ScanFeatures: ...

    def describe_batch(self, scans: list[RadarScan]) -> list[ScanFeatures]: ...


def load_default_extractor(name: str = "default") -> FeatureExtractor:
    """A shipped descriptor model by registry name (``default``: the shipped default) or a ``.pt`` path."""
    from reradar_core.model import DescriptorExtractor

    return DescriptorExtractor.from_pretrained(name)
