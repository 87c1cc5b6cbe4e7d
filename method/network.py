"""DeepLabV3+ pixel-embedding network (plain torch, trained from scratch).

ResNet encoder (BasicBlocks, dilated to output stride 16 or 8), ASPP with atrous rates
6/12/18 plus image pooling, and the DeepLabV3+ decoder that fuses the ASPP output with the
stride-4 low-level features. The classifier is replaced by a 1×1 convolution to ``embed_dim``
channels; the output is upsampled to the input size and L2-normalised per pixel.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

ENCODER_BLOCKS = {"resnet18": (2, 2, 2, 2), "resnet34": (3, 4, 6, 3)}
RGB_MEAN = (0.485, 0.456, 0.406)
RGB_STD = (0.229, 0.224, 0.225)
# [selfseg] input channels after RGB with ``NetConfig.geometry``: the camera-frame unit normal (x, y, z) and the depth
# about the frame's median (features.input_frame); they enter the network as they are, 0 where unknown or masked.
GEOMETRY_CHANNELS = 4


@dataclass
class NetConfig:
    """Architecture of :class:`EmbeddingNet`; ``width`` = 64 and 256-channel heads is standard DeepLabV3+."""

    encoder: str = "resnet18"  # one of ENCODER_BLOCKS
    embed_dim: int = 16
    output_stride: int = 16  # 16 (layer4 dilated) or 8 (layer3 and layer4 dilated)
    aspp_rates: tuple[int, ...] = (6, 12, 18)
    width: int = 64  # channels of the first ResNet stage; stages have width × (1, 2, 4, 8)
    aspp_channels: int = 256
    low_level_channels: int = 48
    decoder_channels: int = 256
    # [selfseg] geometry beside RGB in the input (GEOMETRY_CHANNELS more); False is the paper's φ, which sees RGB only
    geometry: bool = False

    @property
    def in_channels(self) -> int:
        """Channels of the network's input: RGB, then the geometry channels if ``geometry``."""
        return 3 + GEOMETRY_CHANNELS * self.geometry

    def __post_init__(self):
        if self.encoder not in ENCODER_BLOCKS:
            raise ValueError(f"encoder {self.encoder!r} unknown; choose one of {sorted(ENCODER_BLOCKS)}")
        if self.output_stride not in (8, 16):
            raise ValueError(f"output_stride must be 8 or 16, got {self.output_stride}")
        if min(self.embed_dim, self.width, self.aspp_channels, self.low_level_channels, self.decoder_channels) < 1:
            raise ValueError("embed_dim and all channel counts must be positive")

    @classmethod
    def preset(cls, name: str, **overrides) -> "NetConfig":
        """Named architecture: "default" (standard DeepLabV3+ widths) or "fast" (narrower, for CPU inference)."""
        if name not in NET_PRESETS:
            raise ValueError(f"unknown network preset {name!r}; choose one of {sorted(NET_PRESETS)}")
        return cls(**{**NET_PRESETS[name], **overrides})


NET_PRESETS: dict[str, dict] = {
    "default": {},
    "fast": dict(width=32, aspp_channels=128, low_level_channels=32, decoder_channels=64),
}


def _conv_bn_relu(cin: int, cout: int, k: int = 3, dilation: int = 1) -> nn.Sequential:
    pad = dilation * (k // 2)
    return nn.Sequential(nn.Conv2d(cin, cout, k, padding=pad, dilation=dilation, bias=False),
                         nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class BasicBlock(nn.Module):
    """ResNet basic block; ``dilation`` replaces striding in the dilated stages."""

    def __init__(self, cin: int, cout: int, stride: int, dilation: int):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, padding=dilation, dilation=dilation, bias=False)
        self.bn1 = nn.BatchNorm2d(cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, padding=dilation, dilation=dilation, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        nn.init.zeros_(self.bn2.weight)  # each residual branch starts as identity (helps from-scratch training)
        self.down = None
        if stride != 1 or cin != cout:
            self.down = nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = F.relu(self.bn1(self.conv1(x)), inplace=True)
        out = self.bn2(self.conv2(out))
        return F.relu(out + (x if self.down is None else self.down(x)), inplace=True)


class ResNetEncoder(nn.Module):
    """Returns (stride-4 low-level features, deep features at ``output_stride``)."""

    def __init__(self, blocks: tuple[int, ...], width: int, output_stride: int, in_channels: int = 3):
        super().__init__()
        self.stem = nn.Sequential(nn.Conv2d(in_channels, width, 7, 2, 3, bias=False), nn.BatchNorm2d(width),
                                  nn.ReLU(inplace=True), nn.MaxPool2d(3, 2, 1))
        chans = [width, width * 2, width * 4, width * 8]
        dilated = {16: (False, False, True), 8: (False, True, True)}[output_stride]
        layers, cin, dilation = [], width, 1
        for i, (n, cout) in enumerate(zip(blocks, chans)):
            stride = 1 if i == 0 else 2
            if i > 0 and dilated[i - 1]:
                dilation, stride = dilation * 2, 1
            layers.append(nn.Sequential(*[BasicBlock(cin if j == 0 else cout, cout, stride if j == 0 else 1, dilation)
                                          for j in range(n)]))
            cin = cout
        self.layer1, self.layer2, self.layer3, self.layer4 = layers
        self.out_channels = chans[-1]
        self.low_channels = chans[0]

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        low = self.layer1(self.stem(x))
        return low, self.layer4(self.layer3(self.layer2(low)))


class ASPP(nn.Module):
    """Atrous spatial pyramid pooling: 1×1, one 3×3 per rate, image pooling; projected to ``cout``."""

    def __init__(self, cin: int, cout: int, rates: tuple[int, ...]):
        super().__init__()
        self.branches = nn.ModuleList([_conv_bn_relu(cin, cout, 1)] + [_conv_bn_relu(cin, cout, 3, r) for r in rates])
        # No BatchNorm on the pooled branch: a 1×1 map would break batch statistics at batch size 1.
        self.pool = nn.Sequential(nn.AdaptiveAvgPool2d(1), nn.Conv2d(cin, cout, 1), nn.ReLU(inplace=True))
        self.project = _conv_bn_relu(cout * (len(rates) + 2), cout, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        outs = [b(x) for b in self.branches]
        outs.append(self.pool(x).expand(-1, -1, x.shape[2], x.shape[3]))
        return self.project(torch.cat(outs, 1))


class EmbeddingNet(nn.Module):
    """DeepLabV3+ with a ``embed_dim``-channel embedding head.

    forward(x: B×C×H×W float: RGB in [0, 1], then with ``cfg.geometry`` the geometry channels) → B×D×H×W, unit L2
    norm at every pixel.
    """

    def __init__(self, cfg: NetConfig | None = None):
        super().__init__()
        self.cfg = cfg = cfg if cfg is not None else NetConfig()
        self.encoder = ResNetEncoder(ENCODER_BLOCKS[cfg.encoder], cfg.width, cfg.output_stride, cfg.in_channels)
        self.aspp = ASPP(self.encoder.out_channels, cfg.aspp_channels, tuple(cfg.aspp_rates))
        self.low_proj = _conv_bn_relu(self.encoder.low_channels, cfg.low_level_channels, 1)
        self.decoder = nn.Sequential(_conv_bn_relu(cfg.aspp_channels + cfg.low_level_channels, cfg.decoder_channels),
                                     _conv_bn_relu(cfg.decoder_channels, cfg.decoder_channels))
        self.head = nn.Conv2d(cfg.decoder_channels, cfg.embed_dim, 1)
        self.register_buffer("mean", torch.tensor(RGB_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(RGB_STD).view(1, 3, 1, 1), persistent=False)
        for m in self.modules():
            if isinstance(m, nn.Conv2d) and m is not self.head:
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")

    def forward_stride4(self, x: torch.Tensor) -> torch.Tensor:
        """Unnormalised embeddings at stride 4: B×D×ceil(H/4)×ceil(W/4)."""
        c = self.cfg.in_channels
        if x.ndim != 4 or x.shape[1] != c:
            raise ValueError(f"expected B×{c}×H×W input (RGB in [0, 1]{', then geometry' if c > 3 else ''}), "
                             f"got shape {tuple(x.shape)}")
        z = (x - self.mean) / self.std if c == 3 else torch.cat([(x[:, :3] - self.mean) / self.std, x[:, 3:]], 1)
        low, deep = self.encoder(z)
        deep = F.interpolate(self.aspp(deep), size=low.shape[2:], mode="bilinear", align_corners=False)
        return self.head(self.decoder(torch.cat([deep, self.low_proj(low)], 1)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        z = self.forward_stride4(x)
        with torch.autocast(x.device.type, enabled=False):  # under autocast (bf16 training): upsample and
            # normalise in float32
            z = F.interpolate(z.float(), size=x.shape[2:], mode="bilinear", align_corners=False)
            return F.normalize(z, dim=1)
