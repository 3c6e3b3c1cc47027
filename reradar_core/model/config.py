"""Descriptor model configuration (paper, Sec. "Implementation Details").

One frozen dataclass describes an architecture completely: the network can be rebuilt from it (and from the
JSON next to shipped weights) without any training code.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

from reradar_core.errors import ConfigError
from reradar_core.geometry.cartesian import CartesianConfig

__all__ = ["ModelConfig", "BACKBONES", "stage_channels"]

BACKBONES = ("reresnet", "resnet")

# ResNet-50 bottleneck layout up to and including stage 2 (He et al. 2016): stem 64 channels, stage 1 with
# 3 blocks of width 64 (output 64 x 4 = 256), stage 2 with 4 blocks of width 128 (output 512), first block of
# stage 2 strided. Channel counts are *total* channels; for the C8 ReResNet they are regular fields x 8, so
# at width 1.0 stage 2 outputs 512 channels = 64 regular fields (the paper's C = 512 feature maps) and group
# pooling leaves 64 rotation-invariant channels in F'.
_BASE_STEM = 64
_BASE_STAGES = ((64, 3, 1), (128, 4, 2))  # (bottleneck width, blocks, stride of the first block)
_EXPANSION = 4


def stage_channels(width: float, group_order: int) -> tuple[int, list[tuple[int, int, int, int]]]:
    """Total channel counts at a width multiplier, rounded to whole regular fields.

    Returns:
        (stem_channels, [(mid_channels, out_channels, blocks, stride), ...]).
    """

    def rnd(c: float) -> int:
        return max(1, int(round(c * width / group_order))) * group_order

    stages = [(rnd(w), rnd(w * _EXPANSION), n, s) for w, n, s in _BASE_STAGES]
    return rnd(_BASE_STEM), stages


@dataclass(frozen=True)
class ModelConfig:
    """Architecture of a descriptor network.

    Attributes:
        backbone: "reresnet" (C_N steerable convolutions, regular fields, e2cnn) or "resnet" (standard
            convolutions with the same layout and channel counts; the paper's backbone ablation).
        width: width multiplier on the ResNet-50 channel counts (1.0 = full width, 65 ms per 201 x 201
            image on the 2-core CPU; the default 0.5 takes ~31 ms and trains in the CPU budget, see
            docs/MODEL.md).
        group_order: N of the cyclic group C_N (paper: 8).
        stem_kernel: stem convolution size (stride 2), followed by a 3x3 stride-2 max pool.
        num_clusters: NetVLAD clusters K.
        output_dim: PCA-whitening projection output D (None: raw K*C NetVLAD vector).
        cartesian_width_px, cartesian_resolution_m: network input geometry (201 px keeps C8 equivariance
            exact for 90 degree rotations; the paper's 200 does not).
        disc_mask: NetVLAD aggregates only the F' cells inside the sensor disc (the image's inscribed circle;
            soft weight over one cell at the rim), so content that a yaw rotation moves into or out of the
            square's corners does not change the global descriptor. No parameters: weights trained without
            it load unchanged (docs/MODEL.md, "Invariance at any angle").
        disc_mask_input: also zero the input image outside the inscribed circle (off by default; see
            docs/MODEL.md for the measurement).
        canonical_heading: turn every scan to its canonical heading (``geometry.heading.canonical_turn``)
            before the Cartesian image is made, so that the global descriptor of a scan and of any turned copy
            are the same (the network alone is exact only at 90-degree steps); local descriptors are read from F'
            at the turned landmark positions. No parameters. **Off by default**: the heading it reads differs
            between two passes of a place by a median 4-10 degrees, and on an open urban loop that cost the
            descriptor alone 9.7 points (docs/MODEL.md, "A canonical heading"). ``model_id`` ends in ``-ch`` with
            it, so a map described without it refuses queries described with it, and the other way round.
    """

    backbone: str = "reresnet"
    width: float = 0.25
    group_order: int = 8
    stem_kernel: int = 7
    num_clusters: int = 32
    output_dim: int | None = 256
    cartesian_width_px: int = 201
    cartesian_resolution_m: float = 0.64
    disc_mask: bool = True
    disc_mask_input: bool = False
    canonical_heading: bool = False
    extra: dict[str, Any] = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        if self.backbone not in BACKBONES:
            raise ConfigError(f"unknown backbone {self.backbone!r}; choose one of {BACKBONES}")
        if not (0 < self.width <= 4):
            raise ConfigError(f"width multiplier must be in (0, 4], got {self.width}")
        if self.group_order < 1:
            raise ConfigError(f"group order must be >= 1, got {self.group_order}")
        if self.stem_kernel % 2 != 1:
            raise ConfigError(f"stem kernel must be odd, got {self.stem_kernel}")
        if self.num_clusters < 1:
            raise ConfigError(f"NetVLAD needs at least one cluster, got {self.num_clusters}")
        if self.output_dim is not None and self.output_dim < 1:
            raise ConfigError(f"output_dim must be positive or None, got {self.output_dim}")
        for name in ("disc_mask", "disc_mask_input", "canonical_heading"):
            # a JSON "false" (a string) would otherwise read as on
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"{name} must be true or false, got {getattr(self, name)!r}")

    @property
    def cartesian(self) -> CartesianConfig:
        return CartesianConfig(self.cartesian_width_px, self.cartesian_resolution_m)

    @property
    def channels(self) -> tuple[int, list[tuple[int, int, int, int]]]:
        return stage_channels(self.width, self.group_order)

    @property
    def feature_dim(self) -> int:
        """C of F' (local descriptor size): regular fields after group pooling, or channels for ResNet."""
        out = self.channels[1][-1][1]
        return out // self.group_order if self.backbone == "reresnet" else out

    @property
    def vlad_dim(self) -> int:
        return self.num_clusters * self.feature_dim

    @property
    def descriptor_dim(self) -> int:
        return self.output_dim if self.output_dim is not None else self.vlad_dim

    @property
    def stride(self) -> int:
        """Total stride from input pixels to F' cells (stem 2 x pool 2 x stage-2 2 = 8)."""
        s = 4
        for _, _, _, st in self.channels[1]:
            s *= st
        return s

    @property
    def model_id(self) -> str:
        kind = f"reresnet-c{self.group_order}" if self.backbone == "reresnet" else "resnet"
        d = self.output_dim if self.output_dim is not None else "raw"
        ch = "-ch" if self.canonical_heading else ""
        return f"{kind}-w{self.width:g}-k{self.num_clusters}-d{d}-in{self.cartesian_width_px}{ch}"

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d.pop("extra", None)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ModelConfig:
        known = {k: d[k] for k in cls.__dataclass_fields__ if k in d and k != "extra"}
        return cls(**known)
