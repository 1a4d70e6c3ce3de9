"""Data for the height-profile CNN: profilometer height maps, registration, data sets.

Two kinds of training data (paper §5):

* **pairs** (stage 1): a grayscale column across the line from an alignment-camera
  frame and the profilometer's height profile at the same place, resampled onto
  the column's pixel grid;
* **labelled columns** (stage 2): columns with only the computer-vision linewidth
  and overspray (the "CV labels").

Both are stored as NPZ files (see :func:`save_dataset`).

Profilometer exports (Keyence VK-X, KLA Tencor) are plain height grids. We read
CSV/TXT (any of ``, ; tab space`` as separator; non-numeric header lines are
skipped; a header line ``# pixel_size_um = 0.52`` sets the pixel size) and NPZ
(``height`` or ``height_um`` array, ``pixel_size_um`` scalar, optional
``height_unit``).

Registration (:func:`register_profile`)
--------------------------------------
A profilometer cross-section and a camera column are put on one grid by

1. levelling the scan: a straight line fitted to the outer 15 % of samples on
   each side (bare substrate) is subtracted, removing tilt and offset;
2. centring: the line centre in the scan is the area centroid of the positive
   part of the levelled profile; in the frame it is the line's row
   ``line_center_px`` (from the vision line fit; ``(n-1)/2`` for a column already
   cropped around the line);
3. resampling: camera pixel k covers ``[(k−c−½)·s, (k−c+½)·s]`` µm from the line
   centre (s = µm per camera pixel, c = ``line_center_px``); its height is the
   exact mean of the piecewise-linear scan over that interval. Area is
   preserved, so Q_m computed on the registered profile equals the scan's.
   Outside the scan the height is 0 (substrate).

Before step 3 a scan is smoothed with a Gaussian of σ = ``scan_smoothing_um``
(``ajtwin/data/profile_cnn.toml``, 1.25 µm): the edge definitions react to
sub-nm slopes, and the instrument's height noise otherwise puts the features of
the stage-1 targets ~19 µm off the truth (1.2 µm after smoothing; area kept).
"""

from __future__ import annotations

import csv
import re
import warnings
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter1d

from ajtwin.config import packaged_toml
from ajtwin.units import m_to_um, to_si

N_PIXELS = 200
EDGE_FRACTION = 0.15  # outer share of a scan on each side treated as bare substrate


@lru_cache(maxsize=1)
def settings() -> dict:
    """The CNN data-path settings (``ajtwin/data/profile_cnn.toml``)."""
    return packaged_toml("data/profile_cnn.toml")


def default_scan_smoothing_um() -> float:
    """σ (µm) of the Gaussian applied to profilometer scans before registration."""
    return float(settings()["registration"]["scan_smoothing_um"])


def smooth_scan(h_um, pixel_size_um: float, sigma_um: float) -> np.ndarray:
    """Gaussian-smooth a (levelled) cross-section; σ in µm along the scan.

    The ends are continued with their edge value (bare substrate after
    levelling), so the area under the profile is kept. ``sigma_um = 0``
    returns the scan unchanged.
    """
    h = np.asarray(h_um, dtype=float)
    if sigma_um < 0 or not np.isfinite(sigma_um):
        raise ValueError(f"scan smoothing σ must be ≥ 0 µm, got {sigma_um}")
    if sigma_um == 0:
        return h

    return gaussian_filter1d(h, sigma_um / pixel_size_um, mode="nearest", truncate=4.0)


@dataclass
class HeightMap:
    """A profilometer height grid.

    Attributes
    ----------
    height_um : ndarray (n_sections, n_samples)
        Heights in µm. Each row is one cross-section across the line.
    pixel_size_um : float
        Sample spacing across the line (along a row), µm.
    source : str
        File the map came from (for error messages).
    """

    height_um: np.ndarray
    pixel_size_um: float
    source: str = ""

    @property
    def n_sections(self) -> int:
        """Cross-sections in the map."""
        return self.height_um.shape[0]

    def section(self, row: int, n_rows: int = 1) -> np.ndarray:
        """Mean cross-section over rows ``row … row+n_rows−1`` (µm)."""
        if not 0 <= row <= self.n_sections - n_rows:
            raise IndexError(
                f"{self.source}: cross-section rows {row}..{row + n_rows - 1} outside "
                f"0..{self.n_sections - 1}"
            )
        return self.height_um[row : row + n_rows].mean(axis=0)


def _length_to_um(values, unit: str):
    return m_to_um(to_si(values, unit))


_PIXEL_SIZE_RE = re.compile(r"pixel_size_um\s*[=:,;]\s*([0-9.eE+-]+)")


def _read_csv_grid(path: Path) -> tuple[np.ndarray, float | None]:
    text = path.read_text(errors="replace").splitlines()
    pixel_size = None
    rows: list[list[float]] = []
    first_data_line = None
    for lineno, line in enumerate(text, start=1):
        stripped = line.strip()
        if not stripped:
            continue
        m = _PIXEL_SIZE_RE.search(stripped)
        if m and (stripped.startswith("#") or not rows):
            pixel_size = float(m.group(1))
            continue
        if stripped.startswith("#"):
            continue
        dialect_sep = max(",;\t", key=stripped.count)
        fields = stripped.split(dialect_sep) if stripped.count(dialect_sep) else stripped.split()
        fields = [f.strip() for f in fields if f.strip() != ""]
        try:
            values = [float(f) if f.lower() not in ("nan", "") else np.nan for f in fields]
        except ValueError:
            if rows:
                raise ValueError(
                    f"{path}:{lineno}: non-numeric value in height grid: {line[:80]!r}"
                ) from None
            continue  # header line of an instrument export
        if first_data_line is None:
            first_data_line = lineno
        if rows and len(values) != len(rows[0]):
            raise ValueError(
                f"{path}:{lineno}: row has {len(values)} values, expected {len(rows[0])} "
                f"(as on line {first_data_line})"
            )
        rows.append(values)
    if not rows:
        raise ValueError(f"{path}: no numeric height grid found")
    return np.asarray(rows, dtype=float), pixel_size


def load_height_map(
    path,
    pixel_size_um: float | None = None,
    *,
    height_unit: str = "um",
    across_axis: int | str = 1,
    max_nan_fraction: float = 0.2,
) -> HeightMap:
    """Read a profilometer height map from CSV/TXT or NPZ.

    Parameters
    ----------
    path : str or Path
        ``.csv``/``.txt`` plain grid or ``.npz`` (``height``/``height_um``,
        ``pixel_size_um``, optional ``height_unit``).
    pixel_size_um : float, optional
        Sample spacing across the line in µm. Overrides the file's value;
        required when the file does not state it.
    height_unit : str
        Unit of the stored heights (``"um"``, ``"nm"``, ``"mm"``, ``"m"``);
        an NPZ ``height_unit`` entry takes precedence.
    across_axis : 0, 1 or "auto"
        Grid axis that runs across the line. 1 (default): each row is a
        cross-section. ``"auto"``: the axis whose mean profile varies most.
    max_nan_fraction : float
        Cross-sections with more missing samples (NaN, profilometer dropouts)
        are dropped with a warning; fewer are filled by linear interpolation.

    Returns
    -------
    HeightMap

    Raises
    ------
    ValueError
        Unknown format, missing pixel size, ragged rows, non-numeric cells,
        or no usable cross-section — naming the file (and line).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"height map {path} does not exist")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        with np.load(path, allow_pickle=False) as z:
            key = next((k for k in ("height_um", "height", "z") if k in z.files), None)
            if key is None:
                raise ValueError(f"{path}: no 'height_um'/'height' array (has {z.files})")
            grid = np.asarray(z[key], dtype=float)
            file_pixel = float(z["pixel_size_um"]) if "pixel_size_um" in z.files else None
            if key == "height_um":
                height_unit = "um"
            elif "height_unit" in z.files:
                height_unit = str(z["height_unit"])
    elif suffix in (".csv", ".txt", ".tsv", ".dat"):
        grid, file_pixel = _read_csv_grid(path)
    else:
        raise ValueError(f"{path}: unknown height-map format {suffix!r} (use .csv/.txt or .npz)")
    pixel = pixel_size_um if pixel_size_um is not None else file_pixel
    if pixel is None:
        raise ValueError(
            f"{path}: pixel size unknown; pass pixel_size_um (--pixel-size-um) "
            "or add a '# pixel_size_um = …' header line"
        )
    if not (np.isfinite(pixel) and pixel > 0):
        raise ValueError(f"{path}: pixel size must be > 0 µm, got {pixel}")
    if grid.ndim == 1:
        grid = grid[None, :]
    if grid.ndim != 2:
        raise ValueError(f"{path}: height grid must be 2-D, got shape {grid.shape}")
    if across_axis == "auto":
        var_rows = np.nanstd(np.nanmean(grid, axis=0))
        var_cols = np.nanstd(np.nanmean(grid, axis=1))
        across_axis = 1 if var_rows >= var_cols else 0
    if across_axis == 0:
        grid = grid.T
    elif across_axis != 1:
        raise ValueError(f"across_axis must be 0, 1 or 'auto', got {across_axis!r}")
    grid = _length_to_um(grid, height_unit)
    grid = _fill_nans(grid, max_nan_fraction, str(path))
    return HeightMap(height_um=grid, pixel_size_um=float(pixel), source=str(path))


def _fill_nans(grid: np.ndarray, max_nan_fraction: float, source: str) -> np.ndarray:
    bad = ~np.isfinite(grid)
    if not bad.any():
        return grid
    frac = bad.mean(axis=1)
    keep = frac <= max_nan_fraction
    if not keep.any():
        raise ValueError(
            f"{source}: every cross-section has more than {max_nan_fraction:.0%} missing samples"
        )
    if not keep.all():
        dropped = np.flatnonzero(~keep)
        warnings.warn(
            f"{source}: dropped {dropped.size} cross-section(s) with > "
            f"{max_nan_fraction:.0%} missing samples (first: row {dropped[0]})",
            stacklevel=3,
        )
    grid = grid[keep].copy()
    x = np.arange(grid.shape[1])
    for row in grid:
        ok = np.isfinite(row)
        if not ok.all():
            row[~ok] = np.interp(x[~ok], x[ok], row[ok])
    return grid


def level_profile(h_um, edge_fraction: float = EDGE_FRACTION) -> np.ndarray:
    """Subtract the substrate plane: a line fitted to the outer samples of both sides.

    Parameters
    ----------
    h_um : array (n,)
        Raw cross-section, µm.
    edge_fraction : float
        Share of samples on each side taken as bare substrate.

    Returns
    -------
    ndarray (n,)
        Levelled heights, µm (substrate ≈ 0).
    """
    h = np.asarray(h_um, dtype=float)
    n = h.size
    k = max(2, int(round(edge_fraction * n)))
    if 2 * k >= n:
        raise ValueError(f"cross-section of {n} samples too short to level")
    idx = np.r_[0:k, n - k : n]
    slope, offset = np.polyfit(idx, h[idx], 1)
    return h - (slope * np.arange(n) + offset)


def profile_centroid_um(h_um, pixel_size_um: float) -> float:
    """Area centroid of the positive part of a profile, µm from sample 0."""
    h = np.clip(np.asarray(h_um, dtype=float), 0.0, None)
    total = h.sum()
    if total <= 0:
        raise ValueError("profile has no positive height: cannot find the line centre")
    return float(np.sum(np.arange(h.size) * h) / total * pixel_size_um)


def register_profile(
    h_um,
    pixel_size_um: float,
    um_per_px: float,
    *,
    n_pixels: int = N_PIXELS,
    line_center_px: float | None = None,
    profile_center_um: float | None = None,
    level: bool = True,
    smoothing_um: float = 0.0,
) -> np.ndarray:
    """Resample a profilometer cross-section onto a camera column's pixel grid.

    Parameters
    ----------
    h_um : array (m,)
        Cross-section heights, µm, sampled every ``pixel_size_um``.
    pixel_size_um : float
        Profilometer sample spacing, µm.
    um_per_px : float
        Camera pixel size in the frame, µm.
    n_pixels : int
        Length of the camera column (200).
    line_center_px : float, optional
        Row of the line centre in the column (default ``(n_pixels−1)/2``).
    profile_center_um : float, optional
        Line centre in the scan, µm from sample 0 (default: area centroid
        after levelling).
    level : bool
        Level the scan first (see :func:`level_profile`).
    smoothing_um : float
        σ of a Gaussian applied to the levelled scan (:func:`smooth_scan`);
        0 (default) = none. Real and synthetic profilometer scans are
        registered with :func:`default_scan_smoothing_um` (see the module
        docstring); a noiseless reference profile needs none.

    Returns
    -------
    ndarray (n_pixels,)
        Mean height over each camera pixel, µm. ``sum(result) * um_per_px``
        equals the scan's area inside the column's footprint.

    Examples
    --------
    >>> h = np.zeros(400); h[180:220] = 1.0          # 40 samples of 0.5 µm: 20 µm wide
    >>> g = register_profile(h, 0.5, 2.0, n_pixels=50, level=False)
    >>> float(g.sum() * 2.0)                          # area 20 µm² preserved
    20.0
    """
    h = np.asarray(h_um, dtype=float)
    if h.ndim != 1 or h.size < 4:
        raise ValueError(f"cross-section must be 1-D with ≥ 4 samples, got shape {h.shape}")
    if not np.all(np.isfinite(h)):
        raise ValueError("cross-section contains NaN/inf; fill or drop them first")
    if not (pixel_size_um > 0 and um_per_px > 0):
        raise ValueError(f"pixel sizes must be > 0 (scan {pixel_size_um}, camera {um_per_px})")
    if level:
        h = level_profile(h)
    h = smooth_scan(h, pixel_size_um, smoothing_um)
    if profile_center_um is None:
        profile_center_um = profile_centroid_um(h, pixel_size_um)
    if line_center_px is None:
        line_center_px = (n_pixels - 1) / 2
    # Piecewise-linear scan; its exact running integral at the sample points…
    x = np.arange(h.size) * pixel_size_um - profile_center_um
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (h[1:] + h[:-1]) * np.diff(x))])
    # …then the integral up to any r (quadratic inside a segment, constant outside).
    edges = (np.arange(n_pixels + 1) - line_center_px - 0.5) * um_per_px
    return np.diff(_running_integral(x, h, cum, edges)) / um_per_px


def _running_integral(x, h, cum, r):
    r_c = np.clip(r, x[0], x[-1])
    i = np.clip(np.searchsorted(x, r_c, side="right") - 1, 0, x.size - 2)
    dx = r_c - x[i]
    slope = (h[i + 1] - h[i]) / (x[i + 1] - x[i])
    return cum[i] + h[i] * dx + 0.5 * slope * dx**2


def column_from_frame(
    frame,
    column_px: int,
    line_row_px: float,
    *,
    n_pixels: int = N_PIXELS,
    half_width_px: int = 0,
) -> np.ndarray:
    """Cut the grayscale column across a horizontal line out of a frame.

    Parameters
    ----------
    frame : array (rows, cols) or (rows, cols, 3)
        Frame with the line horizontal (rotate it first, e.g. with the vision
        extractor's line fit). Colour frames are converted to gray by mean.
    column_px : int
        Column (position along the line).
    line_row_px : float
        Row of the line centre; the column spans ``n_pixels`` rows centred here.
    half_width_px : int
        Average ``2·half_width_px + 1`` neighbouring columns (noise reduction).

    Returns
    -------
    ndarray (n_pixels,) float
        Intensities, in the frame's own scale (0–255 for 8-bit video).
    """
    img = np.asarray(frame, dtype=float)
    if img.ndim == 3:
        img = img.mean(axis=2)
    top = int(round(line_row_px - (n_pixels - 1) / 2))
    if top < 0 or top + n_pixels > img.shape[0]:
        raise ValueError(
            f"a {n_pixels}-pixel column centred on row {line_row_px:.1f} leaves the "
            f"{img.shape[0]}-row frame"
        )
    lo, hi = column_px - half_width_px, column_px + half_width_px + 1
    if lo < 0 or hi > img.shape[1]:
        raise ValueError(f"columns {lo}..{hi - 1} outside the {img.shape[1]}-column frame")
    return img[top : top + n_pixels, lo:hi].mean(axis=1)


def normalize_columns(columns) -> np.ndarray:
    """Map raw intensities to the network's input scale.

    Each column is divided by its substrate brightness (median of the outer
    5 % of pixels on both sides, beyond any overspray) and shifted so bare
    substrate is 0. This makes the input independent of exposure and gain.

    Parameters
    ----------
    columns : array (..., n_pixels)

    Returns
    -------
    ndarray float32, same shape
    """
    c = np.asarray(columns, dtype=np.float64)
    if not np.all(np.isfinite(c)):
        bad = np.argwhere(~np.isfinite(c))[0]
        raise ValueError(f"column intensities contain NaN/inf (first at index {tuple(bad)})")
    n = c.shape[-1]
    k = max(1, int(round(0.05 * n)))
    background = np.median(np.concatenate([c[..., :k], c[..., -k:]], axis=-1), axis=-1)
    background = np.maximum(background, 1e-6 * max(1.0, float(np.max(np.abs(c)))))
    return (c / background[..., None] - 1.0).astype(np.float32)


# ---------------------------------------------------------------- data set files


@dataclass
class ColumnDataset:
    """Columns across the line with profiles and/or CV labels.

    Attributes
    ----------
    columns : ndarray (N, n_pixels)
        Raw intensities (0–255 for 8-bit frames).
    um_per_px : float
        Camera pixel size, µm.
    profiles_um : ndarray (N, n_pixels), optional
        Registered profilometer heights (stage 1 pairs) or, for synthetic
        data, the hidden true profile (used only for evaluation).
    linewidth_um, overspray_um : ndarray (N,), optional
        CV labels (stage 2).
    group : ndarray (N,) int
        Columns sharing a group (same frame / scan) stay in one CV fold.
    extra : dict
        Further arrays (e.g. ``true_linewidth_um`` for synthetic data).
    """

    columns: np.ndarray
    um_per_px: float
    profiles_um: np.ndarray | None = None
    linewidth_um: np.ndarray | None = None
    overspray_um: np.ndarray | None = None
    group: np.ndarray | None = None
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        self.columns = np.asarray(self.columns, dtype=np.float32)
        if self.columns.ndim != 2:
            raise ValueError(f"columns must be (N, n_pixels), got {self.columns.shape}")
        n = len(self.columns)
        if self.group is None:
            self.group = np.arange(n)
        for name in ("profiles_um", "linewidth_um", "overspray_um", "group"):
            value = getattr(self, name)
            if value is not None and len(value) != n:
                raise ValueError(f"{name} has {len(value)} rows, columns has {n}")
        for name in ("profiles_um", "linewidth_um", "overspray_um"):
            value = getattr(self, name)
            if value is not None:
                value = np.asarray(value, dtype=np.float32)
                setattr(self, name, value)
                if not np.all(np.isfinite(value)):
                    row = int(np.argwhere(~np.isfinite(value))[0][0])
                    raise ValueError(f"{name} has NaN/inf at row {row}")

    def __len__(self) -> int:
        return len(self.columns)

    @property
    def n_pixels(self) -> int:
        """Pixels per column."""
        return self.columns.shape[1]

    def subset(self, index) -> ColumnDataset:
        """The columns at ``index`` (an index array or slice) with their labels."""

        def take(a):
            return None if a is None else a[index]

        return ColumnDataset(
            columns=self.columns[index],
            um_per_px=self.um_per_px,
            profiles_um=take(self.profiles_um),
            linewidth_um=take(self.linewidth_um),
            overspray_um=take(self.overspray_um),
            group=take(self.group),
            extra={k: v[index] for k, v in self.extra.items()},
        )


_CORE_KEYS = ("columns", "um_per_px", "profiles_um", "linewidth_um", "overspray_um", "group")


def save_dataset(dataset: ColumnDataset, path) -> Path:
    """Write a :class:`ColumnDataset` as a compressed NPZ."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {"columns": dataset.columns, "um_per_px": np.float64(dataset.um_per_px)}
    for name in ("profiles_um", "linewidth_um", "overspray_um", "group"):
        value = getattr(dataset, name)
        if value is not None:
            arrays[name] = value
    for key, value in dataset.extra.items():
        arrays[f"extra_{key}"] = value
    np.savez_compressed(path, **arrays)
    return path


def load_dataset(path) -> ColumnDataset:
    """Read a data set written by :func:`save_dataset` (or by hand, same keys)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"data set {path} does not exist")
    with np.load(path, allow_pickle=False) as z:
        if "columns" not in z.files or "um_per_px" not in z.files:
            raise ValueError(f"{path}: needs 'columns' and 'um_per_px' arrays (has {z.files})")
        kwargs = {k: z[k] for k in _CORE_KEYS if k in z.files}
        kwargs["um_per_px"] = float(kwargs["um_per_px"])
        extra = {k.removeprefix("extra_"): z[k] for k in z.files if k.startswith("extra_")}
    try:
        return ColumnDataset(**kwargs, extra=extra)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


# ---------------------------------------------------------------- real-data manifest

MANIFEST_COLUMNS = (
    "frame",
    "column_px",
    "line_row_px",
    "scan",
    "scan_row",
    "scan_pixel_size_um",
)


def pairs_from_manifest(
    manifest_path,
    um_per_px: float,
    *,
    n_pixels: int = N_PIXELS,
    half_width_px: int = 0,
    scan_smoothing_um: float | None = None,
) -> ColumnDataset:
    """Build stage-1 pairs from real frames and profilometer scans.

    The manifest is a CSV with one row per pair and columns
    ``frame`` (image file, line horizontal), ``column_px``, ``line_row_px``,
    ``scan`` (height map file), ``scan_row`` (cross-section in it),
    ``scan_pixel_size_um`` (blank: read from the scan file) and optionally
    ``height_unit`` (default um). Paths are relative to the manifest.
    Frames may differ in size from row to row (each is cut on its own).
    Scans are smoothed with ``scan_smoothing_um`` (default: the packaged
    setting, see :func:`default_scan_smoothing_um`) before registration.

    Returns
    -------
    ColumnDataset with ``columns`` and ``profiles_um``; ``group`` numbers the
    distinct scan files.
    """
    import cv2

    manifest_path = Path(manifest_path)
    with manifest_path.open(newline="") as fh:
        reader = csv.DictReader(fh)
        missing = [c for c in MANIFEST_COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise ValueError(f"{manifest_path}: missing column(s) {missing}")
        rows = list(reader)
    if not rows:
        raise ValueError(f"{manifest_path}: no pairs listed")
    if scan_smoothing_um is None:
        scan_smoothing_um = default_scan_smoothing_um()
    columns, profiles, groups = [], [], []
    scans: dict[str, HeightMap] = {}
    for lineno, row in enumerate(rows, start=2):
        where = f"{manifest_path}:{lineno}"
        try:
            frame_path = manifest_path.parent / row["frame"]
            frame = cv2.imread(str(frame_path), cv2.IMREAD_GRAYSCALE)
            if frame is None:
                raise ValueError(f"cannot read frame image {frame_path}")
            col = column_from_frame(
                frame,
                int(row["column_px"]),
                float(row["line_row_px"]),
                n_pixels=n_pixels,
                half_width_px=half_width_px,
            )
            scan_key = row["scan"]
            if scan_key not in scans:
                px = row["scan_pixel_size_um"].strip()
                scans[scan_key] = load_height_map(
                    manifest_path.parent / scan_key,
                    float(px) if px else None,
                    height_unit=(row.get("height_unit") or "um").strip() or "um",
                )
            hm = scans[scan_key]
            prof = register_profile(
                hm.section(int(row["scan_row"])),
                hm.pixel_size_um,
                um_per_px,
                n_pixels=n_pixels,
                smoothing_um=scan_smoothing_um,
            )
        except (ValueError, IndexError, KeyError) as exc:
            raise ValueError(f"{where}: {exc}") from None
        columns.append(col)
        profiles.append(prof)
        groups.append(list(scans).index(scan_key))
    return ColumnDataset(
        columns=np.array(columns),
        um_per_px=um_per_px,
        profiles_um=np.array(profiles),
        group=np.array(groups),
    )
