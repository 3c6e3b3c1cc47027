"""The rotation-equivariant ReResNet backbone (e2cnn, cyclic group C_N, regular fields) used for training.

Layout (paper, Sec. "Implementation Details"; ReDet's ReResNet-50 up to stage 2): trivial-field input ->
R2Conv k x k stride 2 -> InnerBatchNorm -> ReLU -> PointwiseMaxPool 3x3/2 -> bottleneck stages [3, 4]
(expansion 4, first block of stage 2 strided) -> GroupPooling -> F'. Every module is e2cnn's, so the
network is exactly equivariant to the rotations that map the pixel grid onto itself (multiples of 90 degrees)
whenever each strided layer sees an odd-sized input: W = 201 gives 201 -> 101 -> 51 -> 26.

``EquivariantDescriptorNet.export()`` builds the plain-torch ``DescriptorNet`` (no e2cnn at inference).

e2cnn 0.2.3 works with numpy 2.x / torch 2.x on the paths used here (R2Conv on trivial/regular fields,
InnerBatchNorm, ReLU, PointwiseMaxPool, GroupPooling, export); tests/model covers each of them.
Construction expands the steerable bases and takes seconds: build once and reuse.
"""

from __future__ import annotations

import warnings

import torch
from torch import nn

from reradar_core.model.config import ModelConfig
from reradar_core.model.network import DescriptorNet, NetVLAD, PlainBackbone, PlainBottleneck

__all__ = ["EquivariantBackbone", "EquivariantDescriptorNet", "build_training_net"]

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    from e2cnn import gspaces
    from e2cnn import nn as enn

# e2cnn indexes with uint8 masks during basis expansion; torch warns on every construction.
warnings.filterwarnings("ignore", message="indexing with dtype torch.uint8", category=UserWarning)


class _EqBottleneck(nn.Module):
    def __init__(self, in_type: enn.FieldType, mid: int, out: int, stride: int) -> None:
        super().__init__()
        gs = in_type.gspace
        mid_t = enn.FieldType(gs, [gs.regular_repr] * mid)
        out_t = enn.FieldType(gs, [gs.regular_repr] * out)
        self.in_type, self.out_type = in_type, out_t
        self.conv1 = enn.R2Conv(in_type, mid_t, 1, bias=False)
        self.bn1 = enn.InnerBatchNorm(mid_t)
        self.relu1 = enn.ReLU(mid_t, inplace=True)
        self.conv2 = enn.R2Conv(mid_t, mid_t, 3, stride=stride, padding=1, bias=False)
        self.bn2 = enn.InnerBatchNorm(mid_t)
        self.relu2 = enn.ReLU(mid_t, inplace=True)
        self.conv3 = enn.R2Conv(mid_t, out_t, 1, bias=False)
        self.bn3 = enn.InnerBatchNorm(out_t)
        self.relu3 = enn.ReLU(out_t, inplace=True)
        self.down_conv: enn.R2Conv | None = None
        self.down_bn: enn.InnerBatchNorm | None = None
        if stride != 1 or in_type.size != out_t.size:
            self.down_conv = enn.R2Conv(in_type, out_t, 1, stride=stride, bias=False)
            self.down_bn = enn.InnerBatchNorm(out_t)

    def forward(self, x: enn.GeometricTensor) -> enn.GeometricTensor:
        y = self.relu1(self.bn1(self.conv1(x)))
        y = self.relu2(self.bn2(self.conv2(y)))
        y = self.bn3(self.conv3(y))
        identity = x if self.down_conv is None else self.down_bn(self.down_conv(x))
        return self.relu3(y + identity)

    def export_to(self, plain: PlainBottleneck) -> None:
        _copy(self.conv1, self.bn1, plain.conv1, plain.bn1)
        _copy(self.conv2, self.bn2, plain.conv2, plain.bn2)
        _copy(self.conv3, self.bn3, plain.conv3, plain.bn3)
        if self.down_conv is not None:
            assert plain.downsample is not None
            _copy(self.down_conv, self.down_bn, plain.downsample[0], plain.downsample[1])


def _copy(conv: enn.R2Conv, bn: enn.InnerBatchNorm, pconv: nn.Conv2d, pbn: nn.BatchNorm2d) -> None:
    econv, ebn = conv.export(), bn.export()
    pconv.load_state_dict(econv.state_dict())
    pbn.load_state_dict(ebn.state_dict())


class EquivariantBackbone(nn.Module):
    """C_N-equivariant ReResNet (stem + stages) followed by group pooling: (B, 1, W, W) -> F' (B, C, h, h)."""

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        if config.backbone != "reresnet":
            raise ValueError("EquivariantBackbone is the 'reresnet' backbone")
        self.config = config
        n = config.group_order
        gs = gspaces.Rot2dOnR2(N=n)
        stem, stages = config.channels
        self.in_type = enn.FieldType(gs, [gs.trivial_repr])
        stem_t = enn.FieldType(gs, [gs.regular_repr] * (stem // n))
        k = config.stem_kernel
        self.stem_conv = enn.R2Conv(self.in_type, stem_t, k, stride=2, padding=k // 2, bias=False)
        self.stem_bn = enn.InnerBatchNorm(stem_t)
        self.stem_relu = enn.ReLU(stem_t, inplace=True)
        self.stem_pool = enn.PointwiseMaxPool(stem_t, 3, stride=2, padding=1)
        blocks: list[_EqBottleneck] = []
        t = stem_t
        for mid, out, nblocks, stride in stages:
            for i in range(nblocks):
                blk = _EqBottleneck(t, mid // n, out // n, stride if i == 0 else 1)
                blocks.append(blk)
                t = blk.out_type
        self.blocks = nn.ModuleList(blocks)
        self.out_type = t
        self.gpool = enn.GroupPooling(t)

    def forward_equivariant(self, x: torch.Tensor) -> enn.GeometricTensor:
        """(B, 1, W, W) -> regular-field feature map before group pooling (GeometricTensor)."""
        g = enn.GeometricTensor(x, self.in_type)
        g = self.stem_pool(self.stem_relu(self.stem_bn(self.stem_conv(g))))
        for blk in self.blocks:
            g = blk(g)
        return g

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.gpool(self.forward_equivariant(x)).tensor

    @torch.no_grad()
    def export(self) -> PlainBackbone:
        """Plain-torch copy (eval mode) computing the same function."""
        was_training = self.training
        plain = PlainBackbone(self.config)
        _copy(self.stem_conv, self.stem_bn, plain.stem[0], plain.stem[1])
        plain_blocks = [b for stage in plain.stages for b in stage]
        for eb, pb in zip(self.blocks, plain_blocks, strict=True):
            eb.export_to(pb)
        self.train(was_training)
        return plain.eval()


class EquivariantDescriptorNet(DescriptorNet):
    """Training network for the ReResNet: e2cnn backbone + the plain NetVLAD / projection heads."""

    def __init__(self, config: ModelConfig) -> None:
        super().__init__(config, backbone=EquivariantBackbone(config))

    @torch.no_grad()
    def export(self) -> DescriptorNet:
        """Plain ``DescriptorNet`` (eval mode) with the expanded filters; agrees with this net in eval mode."""
        assert isinstance(self.backbone, EquivariantBackbone)
        plain = DescriptorNet(self.config, backbone=self.backbone.export())
        plain.netvlad.load_state_dict(self.netvlad.state_dict())
        if self.proj is not None:
            assert plain.proj is not None
            plain.proj.load_state_dict(self.proj.state_dict())
        return plain.eval()


def build_training_net(config: ModelConfig) -> DescriptorNet:
    """The trainable network for a config: e2cnn for 'reresnet', plain for 'resnet'.

    Both expose ``forward(x) -> (descriptor, F')``; ``export_plain`` gives the inference network.
    """
    if config.backbone == "reresnet":
        return EquivariantDescriptorNet(config)
    return DescriptorNet(config)


def export_plain(net: DescriptorNet) -> DescriptorNet:
    """Inference copy of a training network (plain torch, eval mode)."""
    if isinstance(net, EquivariantDescriptorNet):
        return net.export()
    plain = DescriptorNet(net.config)
    plain.load_state_dict(net.state_dict())
    return plain.eval()


__all__ += ["export_plain", "NetVLAD"]
