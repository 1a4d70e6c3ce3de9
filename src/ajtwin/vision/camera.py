"""The alignment camera's geometry over the part: the camera file and its transforms.

A frame taken at time ``t`` shows the part around the point ``p(t) + offset_mm``, where
``p(t)`` is the nozzle's position in the program's coordinates
(:meth:`ajtwin.job.Job.state_at`) and ``offset_mm`` the camera's view centre relative to the
nozzle. The image is seen from above, not mirrored: its x axis (columns, to the right)
points along ``(cos θ, sin θ)`` of the program's X-Y plane and its y axis (rows, down)
along ``(sin θ, −cos θ)``, θ = ``rotation_deg`` counter-clockwise from the stage's X
axis. With θ = 0 the frame shows the part as a plot of the program does (X right, Y up).

For the pixel ``(col, row)`` of a ``width_px × height_px`` frame and the view centre
``c = p(t) + offset_mm`` [mm]::

    part = c + (um_per_px / 1000) · [(col − col₀) · e_x + (row − row₀) · e_y]

with ``col₀ = (width_px − 1)/2`` and ``row₀ = (height_px − 1)/2``,

and the inverse projects a part point onto the two image axes. Everything is affine, so
directions (a stroke's tangent, a cross-section's normal) map with the linear part alone.

The camera file (``camera.toml``, docs/reference/camera-file.md)::

    [camera]
    um_per_px = 0.75          # pixel size on the part, µm
    rotation_deg = 0.0        # image x axis from the stage's X axis, counter-clockwise
    offset_mm = [0.0, 0.0]    # view centre relative to the nozzle, program coordinates
    width_px = 1920
    height_px = 1080
    # written by `ajtwin camera calibrate`: standard errors and what the fit used
    um_per_px_se = 0.0004
    rotation_deg_se = 0.01
    offset_mm_se = [0.0002, 0.0003]
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ajtwin.config import InputFileError, read_toml

__all__ = ["Camera", "CameraFileError", "load_camera", "save_camera"]

#: Frame sizes beyond any camera sensor are refused (a unit slip or a typo).
MAX_FRAME_PX = 20_000
#: A view centre further than this from the nozzle is no alignment camera on a stage.
MAX_OFFSET_MM = 1000.0
#: A camera's rotation lies within one turn either way [deg]; calibrate writes -180 to 180.
MAX_ROTATION_DEG = 360.0
#: µm per pixel outside this range is no optical microscope camera over an AJ part.
UM_PER_PX_RANGE = (0.01, 100.0)


class CameraFileError(ValueError):
    """A camera file or camera geometry that cannot be used; the message names the field."""


@dataclass(frozen=True)
class Camera:
    """The alignment camera's geometry (see the module docstring for the conventions).

    Attributes
    ----------
    um_per_px : float
        Pixel size on the part, µm.
    rotation_deg : float
        Image x axis relative to the stage's X axis, counter-clockwise, degrees.
    offset_mm : (float, float)
        View centre relative to the nozzle, program coordinates, mm.
    width_px, height_px : int
        Frame size, pixels.
    um_per_px_se, rotation_deg_se : float or None
        Standard errors from a calibration (None: not calibrated).
    offset_mm_se : (float, float) or None
    calibration : dict
        What a calibration used (video, program, frames, points, residual); free-form.

    Examples
    --------
    >>> cam = Camera(um_per_px=1.0, rotation_deg=90.0, offset_mm=(0.5, 0.0),
    ...              width_px=101, height_px=51)
    >>> col, row = cam.part_to_pixel(0.5, 0.01, nozzle_mm=(0.0, 0.0))
    >>> round(float(col), 6), round(float(row), 6)
    (60.0, 25.0)
    >>> x, y = cam.pixel_to_part(col, row, nozzle_mm=(0.0, 0.0))
    >>> round(float(x), 9), round(float(y), 9)
    (0.5, 0.01)
    """

    um_per_px: float
    rotation_deg: float = 0.0
    offset_mm: tuple[float, float] = (0.0, 0.0)
    width_px: int = 1920
    height_px: int = 1080
    um_per_px_se: float | None = None
    rotation_deg_se: float | None = None
    offset_mm_se: tuple[float, float] | None = None
    calibration: dict = field(default_factory=dict, compare=False)

    def __post_init__(self):
        object.__setattr__(self, "offset_mm", tuple(float(v) for v in self.offset_mm))
        if self.offset_mm_se is not None:
            object.__setattr__(self, "offset_mm_se", tuple(float(v) for v in self.offset_mm_se))
        self.validate()

    # -- checks ----------------------------------------------------------------------------
    def validate(self, where: str = "camera") -> None:
        """Refuse geometry no camera has, naming the field (zero scale, NaN, tiny frame...)."""
        low, high = UM_PER_PX_RANGE
        if not (isinstance(self.um_per_px, (int, float)) and math.isfinite(self.um_per_px)):
            raise CameraFileError(f"{where}: um_per_px must be a number, got {self.um_per_px!r}")
        if not low <= self.um_per_px <= high:
            raise CameraFileError(
                f"{where}: um_per_px = {self.um_per_px:g} µm per pixel is no camera over an "
                f"AJ part (expected {low:g}-{high:g}; 0 means the scale was never calibrated)"
            )
        if not math.isfinite(self.rotation_deg):
            raise CameraFileError(f"{where}: rotation_deg must be finite, got {self.rotation_deg}")
        if abs(self.rotation_deg) > MAX_ROTATION_DEG:
            # 1e300° is some angle, but no one meant it: the digits say nothing of the camera
            raise CameraFileError(
                f"{where}: rotation_deg = {self.rotation_deg:g}° is not a camera's angle "
                f"(expected -{MAX_ROTATION_DEG:g} to {MAX_ROTATION_DEG:g}°)"
            )
        if len(self.offset_mm) != 2 or not all(
            math.isfinite(v) and abs(v) <= MAX_OFFSET_MM for v in self.offset_mm
        ):
            raise CameraFileError(
                f"{where}: offset_mm must be two finite numbers [dx, dy] within "
                f"±{MAX_OFFSET_MM:g} mm, got {list(self.offset_mm)}"
            )
        for name in ("width_px", "height_px"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise CameraFileError(f"{where}: {name} must be an integer, got {value!r}")
            if not 16 <= value <= MAX_FRAME_PX:
                raise CameraFileError(
                    f"{where}: {name} = {value} px is outside 16-{MAX_FRAME_PX} px"
                )
        for name in ("um_per_px_se", "rotation_deg_se"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value >= 0):
                raise CameraFileError(f"{where}: {name} must be >= 0, got {value}")
        if self.offset_mm_se is not None and (
            len(self.offset_mm_se) != 2
            or not all(math.isfinite(v) and v >= 0 for v in self.offset_mm_se)
        ):
            raise CameraFileError(
                f"{where}: offset_mm_se must be two numbers >= 0, got {self.offset_mm_se}"
            )

    # -- geometry --------------------------------------------------------------------------
    @property
    def axes(self) -> np.ndarray:
        """(2, 2) array: rows are the image x and y axes as unit vectors of the part plane."""
        theta = math.radians(self.rotation_deg)
        c, s = math.cos(theta), math.sin(theta)
        return np.array([[c, s], [s, -c]])

    @property
    def centre_px(self) -> tuple[float, float]:
        """Pixel (col, row) of the view centre."""
        return 0.5 * (self.width_px - 1), 0.5 * (self.height_px - 1)

    @property
    def mm_per_px(self) -> float:
        """Pixel size on the part, mm."""
        return self.um_per_px * 1e-3

    @property
    def half_diagonal_mm(self) -> float:
        """From the view centre to a frame corner, mm."""
        return 0.5 * math.hypot(self.width_px, self.height_px) * self.mm_per_px

    def view_centre(self, nozzle_mm) -> np.ndarray:
        """Part point under the frame centre: ``nozzle + offset`` (broadcasts, last axis 2)."""
        return np.asarray(nozzle_mm, dtype=float) + np.asarray(self.offset_mm)

    def part_to_pixel(self, x_mm, y_mm, nozzle_mm) -> tuple[np.ndarray, np.ndarray]:
        """Pixel (col, row) of part points, for the nozzle at ``nozzle_mm`` = (x, y)."""
        cx, cy = self.view_centre(nozzle_mm)
        dx = (np.asarray(x_mm, dtype=float) - cx) / self.mm_per_px
        dy = (np.asarray(y_mm, dtype=float) - cy) / self.mm_per_px
        (ax, ay), (bx, by) = self.axes
        col0, row0 = self.centre_px
        return col0 + dx * ax + dy * ay, row0 + dx * bx + dy * by

    def pixel_to_part(self, col, row, nozzle_mm) -> tuple[np.ndarray, np.ndarray]:
        """Part point (x, y) [mm] of pixels (col, row), for the nozzle at ``nozzle_mm``."""
        cx, cy = self.view_centre(nozzle_mm)
        col0, row0 = self.centre_px
        u = (np.asarray(col, dtype=float) - col0) * self.mm_per_px
        v = (np.asarray(row, dtype=float) - row0) * self.mm_per_px
        (ax, ay), (bx, by) = self.axes
        return cx + u * ax + v * bx, cy + u * ay + v * by

    def part_to_pixel_matrix(self, nozzle_mm) -> np.ndarray:
        """2x3 affine matrix: [col, row] = M @ [x_mm, y_mm, 1] (for cv2.transform)."""
        cx, cy = self.view_centre(nozzle_mm)
        linear = self.axes / self.mm_per_px
        col0, row0 = self.centre_px
        shift = np.array([col0, row0]) - linear @ np.array([cx, cy])
        return np.hstack([linear, shift[:, None]])

    # -- the file --------------------------------------------------------------------------
    def to_toml(self) -> str:
        """The camera file's text (see :func:`save_camera`)."""
        lines = [
            "# Alignment-camera geometry over the part (ajtwin; docs/reference/camera-file.md).",
            "# Frame at time t shows the part around nozzle(t) + offset_mm; image x axis at",
            "# rotation_deg counter-clockwise from the stage's X axis, image seen from above.",
            "[camera]",
            f"um_per_px = {_num(self.um_per_px)}",
            f"rotation_deg = {_num(self.rotation_deg)}",
            f"offset_mm = [{_num(self.offset_mm[0])}, {_num(self.offset_mm[1])}]",
            f"width_px = {int(self.width_px)}",
            f"height_px = {int(self.height_px)}",
        ]
        if self.um_per_px_se is not None:
            lines.append(f"um_per_px_se = {_num(self.um_per_px_se)}")
        if self.rotation_deg_se is not None:
            lines.append(f"rotation_deg_se = {_num(self.rotation_deg_se)}")
        if self.offset_mm_se is not None:
            lines.append(
                f"offset_mm_se = [{_num(self.offset_mm_se[0])}, {_num(self.offset_mm_se[1])}]"
            )
        if self.calibration:
            lines += ["", "[calibration]"]
            for key, value in self.calibration.items():
                lines.append(f"{key} = {_toml_value(value)}")
        return "\n".join(lines) + "\n"


def _num(value: float) -> str:
    return repr(float(value))


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        return _num(value) if math.isfinite(value) else '"nan"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    text = str(value).replace("\\", "\\\\").replace('"', '\\"').replace("\n", " ")
    return f'"{text}"'


_KNOWN = {
    "um_per_px",
    "rotation_deg",
    "offset_mm",
    "width_px",
    "height_px",
    "um_per_px_se",
    "rotation_deg_se",
    "offset_mm_se",
}


def load_camera(path: str | Path) -> Camera:
    """Read a camera file (``[camera]`` table; ``[calibration]`` kept as provenance).

    Raises
    ------
    FileNotFoundError
        No such file.
    CameraFileError
        Not TOML, no ``[camera]`` table, a missing, unknown or impossible field (zero or
        negative scale, NaN, a frame size that is not a whole number of pixels ...); the
        message names the file and the field.
    """
    path = Path(path)
    try:
        data = read_toml(path, what="camera")
    except InputFileError as exc:
        raise CameraFileError(str(exc)) from None
    table = data.get("camera")
    if not isinstance(table, dict):
        raise CameraFileError(
            f"{path}: no [camera] table (expected um_per_px, rotation_deg, offset_mm, "
            "width_px, height_px)"
        )
    unknown = sorted(set(table) - _KNOWN)
    if unknown:
        raise CameraFileError(
            f"{path}: [camera] has unknown field(s) {unknown}; known: {sorted(_KNOWN)}"
        )
    missing = [k for k in ("um_per_px", "offset_mm", "width_px", "height_px") if k not in table]
    if missing:
        raise CameraFileError(f"{path}: [camera] lacks {missing}")
    for key in ("um_per_px", "rotation_deg", "um_per_px_se", "rotation_deg_se"):
        if key in table and (
            isinstance(table[key], bool) or not isinstance(table[key], (int, float))
        ):
            raise CameraFileError(f"{path}: [camera] {key} must be a number, got {table[key]!r}")
    for key in ("offset_mm", "offset_mm_se"):
        if key in table and not (
            isinstance(table[key], list)
            and len(table[key]) == 2
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in table[key])
        ):
            raise CameraFileError(
                f"{path}: [camera] {key} must be two numbers [dx, dy] in mm, got {table[key]!r}"
            )
    try:
        return Camera(
            um_per_px=float(table["um_per_px"]),
            rotation_deg=float(table.get("rotation_deg", 0.0)),
            offset_mm=tuple(table["offset_mm"]),
            width_px=table["width_px"],
            height_px=table["height_px"],
            um_per_px_se=table.get("um_per_px_se"),
            rotation_deg_se=table.get("rotation_deg_se"),
            offset_mm_se=tuple(table["offset_mm_se"]) if "offset_mm_se" in table else None,
            calibration=dict(data.get("calibration", {})),
        )
    except CameraFileError as exc:
        raise CameraFileError(str(exc).replace("camera:", f"{path}: [camera]", 1)) from None


def save_camera(camera: Camera, path: str | Path) -> Path:
    """Write a camera file (atomically: a killed write leaves the old file whole)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(camera.to_toml(), encoding="utf-8")
    tmp.replace(path)
    return path
