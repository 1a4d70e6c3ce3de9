"""1-D ResNet-18 that maps a grayscale column across the line to a height profile.

Paper §5 (SPEC §9): "A ResNet-18 model was selected as the network architecture,
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
    """

    n_pixels: int = 200
    base_channels: int = 64
    blocks_per_stage: tuple[int, ...] = (2, 2, 2, 2)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["blocks_per_stage"] = list(self.blocks_per_stage)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> NetworkConfig:
        d = dict(d)
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
        if x.dim() == 2:
            x = x.unsqueeze(1)
        if x.shape[-1] != self.config.n_pixels:
            raise ValueError(
                f"column has {x.shape[-1]} pixels; this network takes {self.config.n_pixels}"
            )
        features = self.pool(self.stages(self.stem(x))).flatten(1)
        return self.head(features)


def count_parameters(module: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)
