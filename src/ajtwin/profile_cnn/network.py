"""1-D ResNet-18 that maps a grayscale column across the line to a height profile.

Paper §5 (model reference §9): "A ResNet-18 model was selected as the network architecture,
with the input consisting of grayscale image columns of size (200, 1) … we modify
the final layer with a dense linear layer to enable direct height regression."

The topology is He et al. 2016's ResNet-18 with every 2-D operation replaced by
its 1-D counterpart: a 7-tap stride-2 stem and a stride-2 max-pool, then four
stages of two basic blocks (64, 128, 256, 512 channels; stride 2 at the start of
stages 2–4, 1×1 projection shortcuts where the shape changes), global average
pooling and a linear head. The head's outputs are the height profile in µm on the
same pixel grid as the input column. torchvision's ResNet is 2-D only, so the
block is written here.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn


@dataclass(frozen=True)
class NetworkConfig:
    """Shape of the network; stored inside every checkpoint.

    Parameters
    ----------
    n_pixels : int
        Length of the input column and of the output profile (paper: 200).
    base_channels : int
        Channels of the first stage; stages have 1×, 2×, 4×, 8× this
        (ResNet-18: 64 → 64–512 channels).
    blocks_per_stage : tuple of int
        Basic blocks per stage (ResNet-18: 2, 2, 2, 2).
    arch : {"resnet18", "unet1d"}
        The paper's ResNet-18 or the small 1-D U-Net (:class:`UNet1dProfile`).
    depth : int
        U-Net only: number of 2× down-samplings (``n_pixels`` must divide by 2**depth).
    """

    n_pixels: int = 200
    base_channels: int = 64
    blocks_per_stage: tuple[int, ...] = (2, 2, 2, 2)
    arch: str = "resnet18"
    depth: int = 3

    def to_dict(self) -> dict:
        """The configuration as plain values (saved with the model)."""
        d = asdict(self)
        d["blocks_per_stage"] = list(self.blocks_per_stage)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> NetworkConfig:
        """A configuration saved by :meth:`to_dict` (older models: the ResNet)."""
        d = dict(d)  # models saved before the U-Net option have no arch/depth: ResNet
        d["blocks_per_stage"] = tuple(d["blocks_per_stage"])
        return cls(**d)


class BasicBlock1d(nn.Module):
    """ResNet basic block in 1-D: two 3-tap convolutions with batch norm.

    The shortcut is the identity unless the stride or channel count changes,
    in which case it is a 1×1 strided convolution with batch norm (ResNet "B").
    """

    def __init__(self, in_channels: int, out_channels: int, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv1d(in_channels, out_channels, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm1d(out_channels)
        self.conv2 = nn.Conv1d(out_channels, out_channels, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm1d(out_channels)
        self.relu = nn.ReLU(inplace=True)
        if stride != 1 or in_channels != out_channels:
            self.shortcut = nn.Sequential(
                nn.Conv1d(in_channels, out_channels, 1, stride, bias=False),
                nn.BatchNorm1d(out_channels),
            )
        else:
            self.shortcut = nn.Identity()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Two convolutions with a residual connection: (N, C_in, L) → (N, C_out, L')."""
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + self.shortcut(x))


class ResNet18Profile(nn.Module):
    """1-D ResNet-18 with a linear regression head for the height profile.

    Parameters
    ----------
    config : NetworkConfig, optional
        Network shape; the default is the paper's (200 pixels, 64–512 channels).

    Notes
    -----
    Input: ``(batch, n_pixels)`` or ``(batch, 1, n_pixels)`` normalized
    intensities (see :func:`ajtwin.profile_cnn.data.normalize_columns`).
    Output: ``(batch, n_pixels)`` heights in the network's internal scale;
    :class:`ajtwin.profile_cnn.model.ProfileModel` converts to µm.

    Examples
    --------
    >>> net = ResNet18Profile()
    >>> net(torch.zeros(2, 200)).shape
    torch.Size([2, 200])
    """

    def __init__(self, config: NetworkConfig | None = None):
        super().__init__()
        self.config = config or NetworkConfig()
        c = self.config.base_channels
        self.stem = nn.Sequential(
            nn.Conv1d(1, c, 7, 2, 3, bias=False),
            nn.BatchNorm1d(c),
            nn.ReLU(inplace=True),
            nn.MaxPool1d(3, 2, 1),
        )
        stages = []
        in_channels = c
        for i, n_blocks in enumerate(self.config.blocks_per_stage):
            out_channels = c * 2**i
            blocks = []
            for j in range(n_blocks):
                stride = 2 if (i > 0 and j == 0) else 1
                blocks.append(BasicBlock1d(in_channels, out_channels, stride))
                in_channels = out_channels
            stages.append(nn.Sequential(*blocks))
        self.stages = nn.Sequential(*stages)
        self.pool = nn.AdaptiveAvgPool1d(1)
        self.head = nn.Linear(in_channels, self.config.n_pixels)
        for m in self.modules():
            if isinstance(m, nn.Conv1d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm1d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)
        # Zero-init the last BN of each block (Goyal et al. 2017): every block
        # starts as the identity, which trains small data sets more stably.
        for m in self.modules():
            if isinstance(m, BasicBlock1d):
                nn.init.zeros_(m.bn2.weight)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Columns (N, L) or (N, 1, L) → height profiles (N, L) [scaled units]."""
        if x.dim() == 2:
            x = x.unsqueeze(1)
        if x.shape[-1] != self.config.n_pixels:
            raise ValueError(
                f"column has {x.shape[-1]} pixels; this network takes {self.config.n_pixels}"
            )
        features = self.pool(self.stages(self.stem(x))).flatten(1)
        return self.head(features)


class ConvBlock1d(nn.Sequential):
    """Two 3-tap convolutions, each with batch norm and ReLU (the U-Net's unit)."""

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__(
            nn.Conv1d(in_channels, out_channels, 3, 1, 1, bias=False),
            nn.BatchNorm1d(out_channels),
            nn.ReLU(inplace=True),
            nn.Conv1d(out_channels, out_channels, 3, 1, 1, bias=False),
            nn.BatchNorm1d(out_channels),
            nn.ReLU(inplace=True),
        )


class UNet1dProfile(nn.Module):
    """Small 1-D U-Net (Ronneberger et al. 2015): a simpler model than the paper's ResNet.

    The ResNet's global average pool squeezes the column into one vector and a
    dense head re-creates 200 heights, so an edge's position must survive a
    7-sample bottleneck. A U-Net keeps full resolution through skip
    connections and predicts each height from a local window (receptive field
    ±46 pixels at depth 3), which is what the edge definitions need.

    Encoder: ``depth`` levels of :class:`ConvBlock1d` + 2× max-pool with
    c, 2c, 4c … channels, a bottleneck block with ``c·2**depth``; decoder:
    2× transposed convolution, concatenation with the encoder's skip, a block;
    a 1×1 convolution gives one height per pixel (same scale convention as
    :class:`ResNet18Profile`).

    Examples
    --------
    >>> net = UNet1dProfile(NetworkConfig(arch="unet1d", base_channels=16))
    >>> net(torch.zeros(2, 200)).shape
    torch.Size([2, 200])
    """

    def __init__(self, config: NetworkConfig):
        super().__init__()
        self.config = config
        n, depth, c = config.n_pixels, config.depth, config.base_channels
        if depth < 1 or n % 2**depth:
            raise ValueError(f"a depth-{depth} U-Net needs n_pixels divisible by {2**depth}")
        widths = [c * 2**i for i in range(depth + 1)]
        self.down = nn.ModuleList()
        in_ch = 1
        for w in widths[:-1]:
            self.down.append(ConvBlock1d(in_ch, w))
            in_ch = w
        self.pool = nn.MaxPool1d(2)
        self.bottom = ConvBlock1d(widths[-2], widths[-1])
        self.up = nn.ModuleList()
        self.merge = nn.ModuleList()
        for hi, lo in zip(widths[:0:-1], widths[-2::-1], strict=True):
            self.up.append(nn.ConvTranspose1d(hi, lo, 2, stride=2))
            self.merge.append(ConvBlock1d(2 * lo, lo))
        self.head = nn.Conv1d(widths[0], 1, 1)
        for m in self.modules():
            if isinstance(m, nn.Conv1d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
        nn.init.zeros_(self.head.weight)  # start from a flat profile, like a blank prior
        nn.init.zeros_(self.head.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Columns (N, L) or (N, 1, L) → height profiles (N, L) [scaled units]."""
        if x.dim() == 2:
            x = x.unsqueeze(1)
        if x.shape[-1] != self.config.n_pixels:
            raise ValueError(
                f"column has {x.shape[-1]} pixels; this network takes {self.config.n_pixels}"
            )
        skips = []
        for block in self.down:
            x = block(x)
            skips.append(x)
            x = self.pool(x)
        x = self.bottom(x)
        for up, merge, skip in zip(self.up, self.merge, reversed(skips), strict=True):
            x = merge(torch.cat([up(x), skip], dim=1))
        return self.head(x)[:, 0]


ARCHS = {"resnet18": ResNet18Profile, "unet1d": UNet1dProfile}
DEFAULT_WIDTH = {"resnet18": 64, "unet1d": 16}


def build_network(config: NetworkConfig) -> nn.Module:
    """The network named by ``config.arch``."""
    if config.arch not in ARCHS:
        raise ValueError(f"unknown network {config.arch!r} (choose from {', '.join(ARCHS)})")
    return ARCHS[config.arch](config)


def count_parameters(module: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)
