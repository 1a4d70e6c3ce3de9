"""The trained height-profile model: network + input normalization + height scale.

A :class:`ProfileModel` is what ``model.pt`` holds. It takes raw grayscale
columns (any exposure; see :func:`~ajtwin.profile_cnn.data.normalize_columns`)
and returns height profiles in µm on the column's pixel grid.
"""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np
import torch

from ajtwin.profile_cnn.data import normalize_columns
from ajtwin.profile_cnn.flow import material_flow_ml_s
from ajtwin.profile_cnn.network import NetworkConfig, build_network

FORMAT_VERSION = 1


def set_threads(n_threads: int | None = None) -> int:
    """Set PyTorch's intra-op threads (default 1, or ``$AJTWIN_TORCH_THREADS``).

    One thread is the default because on a shared 2-core machine two OpenMP
    threads were 6–20× *slower* than one (barrier spinning when other
    processes hold the cores); give 2 on an idle machine.
    """

    if n_threads is None:
        n_threads = int(os.environ.get("AJTWIN_TORCH_THREADS", 1))
    torch.set_num_threads(max(1, n_threads))
    return torch.get_num_threads()


class ProfileModel:
    """Height-profile regressor ready for inference.

    Parameters
    ----------
    network : ResNet18Profile or UNet1dProfile
    um_per_px : float
        Camera pixel size the network was trained at, µm.
    height_scale_um : float
        The network predicts ``h / height_scale_um`` (keeps outputs O(1)).
    meta : dict, optional
        Provenance (training command, seed, data set sizes, metrics).

    Examples
    --------
    >>> from ajtwin.profile_cnn.network import ResNet18Profile
    >>> m = ProfileModel(ResNet18Profile(NetworkConfig(base_channels=8)), 1.0, 2.0)
    >>> m.predict_um(np.full((3, 200), 120.0)).shape
    (3, 200)
    """

    def __init__(
        self,
        network: torch.nn.Module,
        um_per_px: float,
        height_scale_um: float,
        meta: dict | None = None,
    ):
        self.network = network
        self.um_per_px = float(um_per_px)
        self.height_scale_um = float(height_scale_um)
        self.meta = dict(meta or {})

    @property
    def n_pixels(self) -> int:
        """Pixels per column the network takes."""
        return self.network.config.n_pixels

    def forward_um(self, normalized: torch.Tensor) -> torch.Tensor:
        """Differentiable: normalized columns (tensor) → heights in µm.

        Heights are clamped at 0 (the levelled substrate): a deposit has no
        negative height, and nm-level negative wiggles of the regression on
        bare substrate would otherwise count as slopes — the overspray
        definition (brightness back within 95 % of background, i.e. slopes
        below ~0.6 nm per 0.75 µm pixel) reacts to those.
        """
        return torch.clamp(self.network(normalized) * self.height_scale_um, min=0.0)

    @torch.no_grad()
    def predict_um(self, columns, batch_size: int = 512) -> np.ndarray:
        """Raw intensity columns (N, n_pixels) → height profiles (N, n_pixels) in µm."""
        columns = np.asarray(columns)
        if columns.ndim == 1:
            return self.predict_um(columns[None], batch_size)[0]
        if columns.shape[-1] != self.n_pixels:
            raise ValueError(
                f"columns have {columns.shape[-1]} pixels; the model takes {self.n_pixels}"
            )
        x = torch.from_numpy(normalize_columns(columns))
        was_training = self.network.training
        self.network.eval()
        out = [self.forward_um(x[i : i + batch_size]) for i in range(0, len(x), batch_size)]
        self.network.train(was_training)
        if not out:
            return np.zeros((0, self.n_pixels), dtype=np.float32)
        return torch.cat(out).numpy()

    def material_flow_ml_s(self, columns, platen_speed_mm_s) -> np.ndarray:
        """Q_m per column from predicted profiles (mL/s)."""
        return material_flow_ml_s(self.predict_um(columns), self.um_per_px, platen_speed_mm_s)

    # ------------------------------------------------------------ persistence

    def state(self) -> dict:
        """Everything needed to restore the model (torch.save-able)."""
        return {
            "format_version": FORMAT_VERSION,
            "network_config": self.network.config.to_dict(),
            "state_dict": self.network.state_dict(),
            "um_per_px": self.um_per_px,
            "height_scale_um": self.height_scale_um,
            "meta": self.meta,
        }

    @classmethod
    def from_state(cls, state: dict) -> ProfileModel:
        """The model saved as :attr:`state` (ValueError for another format version)."""
        if state.get("format_version") != FORMAT_VERSION:
            raise ValueError(
                f"model format {state.get('format_version')!r}; this ajtwin reads {FORMAT_VERSION}"
            )
        net = build_network(NetworkConfig.from_dict(state["network_config"]))
        net.load_state_dict(state["state_dict"])
        net.eval()
        return cls(net, state["um_per_px"], state["height_scale_um"], state.get("meta"))

    def save(self, path) -> Path:
        """Write the model (weights + normalization + provenance) to ``path``."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        buffer = io.BytesIO()
        torch.save(self.state(), buffer)
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_bytes(buffer.getvalue())
        tmp.replace(path)  # atomic: a crash never leaves half a model
        return path

    @classmethod
    def load(cls, path) -> ProfileModel:
        """Read a model written by :meth:`save` (or a training checkpoint)."""
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"model file {path} does not exist")
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:
            raise ValueError(f"{path}: not a readable ajtwin CNN model ({exc})") from None
        if "model" in state and "network_config" not in state:  # a training checkpoint
            state = state["model"]
        try:
            return cls.from_state(state)
        except (KeyError, RuntimeError, ValueError) as exc:
            raise ValueError(f"{path}: not an ajtwin CNN model ({exc})") from None
