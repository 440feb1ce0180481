"""Scenes: linear radiance maps in front of the rig.

A scene is a float32 radiance map ``(height, width)``, linear in the light that
reaches the first LCD panel, with its unit and, for test charts, the regions of
interest and true radiance of each patch. Three sources:

- :func:`step_chart`: the 36-level neutral-density step chart of the paper (Wu et
  al., Optics Express 32(11), 2024) in front of a 160,000 lux light box; patch ``i``
  has radiance ``illuminance_lux * 10**(-D_i)``;
- :func:`flat_field`: a uniform field (threshold calibration, the c-map);
- :func:`from_radiance_map`: a real HDR luminance map (read by
  :mod:`asynhdr.io.images`) resized to the sensor with its aspect kept (padded or
  cropped, never stretched unless asked), put in absolute units by
  :func:`exposure_scale`.

Everything here is pure: no file access.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

import cv2
import numpy as np
import numpy.typing as npt

__all__ = [
    "PAPER_DENSITIES",
    "PAPER_ILLUMINANCE_LUX",
    "REC709_LUMA",
    "MovingScene",
    "Roi",
    "Scene",
    "exposure_scale",
    "flat_field",
    "from_radiance_map",
    "log_average",
    "luminance",
    "moving_scene",
    "step_chart",
]

Roi = tuple[int, int, int, int]
"""A region of interest ``(y0, y1, x0, x1)``, half-open: ``image[y0:y1, x0:x1]``."""

PAPER_DENSITIES: tuple[float, ...] = (
    0.00, 0.10, 0.20, 0.30, 0.40, 0.50, 1.20, 1.30, 1.50, 0.60, 0.70, 0.80,
    0.90, 1.00, 1.10, 1.70, 1.90, 2.10, 2.30, 2.50, 2.70, 2.90, 3.43, 3.73,
    4.02, 4.32, 4.63, 4.92, 5.23, 5.52, 5.82, 6.27, 6.72, 7.17, 7.63, 8.22,
)
"""Optical densities ``D`` of the paper's 36-level step chart, level 1 to 36 in order.

Level ``n`` is patch index ``n - 1``; its transmittance is ``10**(-D)``.
"""

PAPER_ILLUMINANCE_LUX: float = 160_000.0
"""Illuminance of the light box behind the paper's step chart, in lux."""

REC709_LUMA: tuple[float, float, float] = (0.2126, 0.7152, 0.0722)
"""Relative luminance weights of linear R, G, B with Rec. 709 / sRGB primaries."""

_MIN_ROI_PX = 1
"""Smallest ROI side, in pixels, that :func:`step_chart` accepts."""


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.array(a, copy=True)
    a.flags.writeable = False
    return a


@dataclass(frozen=True, eq=False)
class Scene:
    """A static scene: a linear radiance map and what is known about it.

    Attributes
    ----------
    radiance:
        ``L(y, x)``, float32 ``(height, width)``, linear, finite, non-negative, in
        ``unit``. Stored as a read-only copy.
    unit:
        Unit of ``radiance``: ``"lux"`` (the light box's illuminance times the
        chart's transmittance) or ``"relative"`` (no absolute calibration).
    name:
        A short label (``"step_chart"``, a file stem, ...).
    rois:
        Optional mapping patch index → ``(y0, y1, x0, x1)`` (half-open) region of
        interest, inside its patch, over which patch statistics (mean, SNR) are taken.
    truth:
        Optional float64 array of the true radiance of each patch, in ``unit``,
        indexed like ``rois``.
    densities:
        Optional float64 array of the optical density ``D`` of each patch.
    """

    radiance: np.ndarray
    unit: str = "relative"
    name: str = ""
    rois: Mapping[int, Roi] | None = None
    truth: np.ndarray | None = None
    densities: np.ndarray | None = None

    def __post_init__(self) -> None:
        r = np.asarray(self.radiance)
        if r.ndim != 2:
            raise ValueError(
                f"Scene.radiance: expected a 2-D (height, width) array, got shape {r.shape}"
            )
        if r.shape[0] < 1 or r.shape[1] < 1:
            raise ValueError(f"Scene.radiance: empty array of shape {r.shape}")
        if not np.issubdtype(r.dtype, np.floating) and not np.issubdtype(r.dtype, np.integer):
            raise ValueError(f"Scene.radiance: expected a real numeric array, got {r.dtype}")
        r = r.astype(np.float32, copy=False)
        _check_finite_nonnegative(r, "Scene.radiance")
        object.__setattr__(self, "radiance", _readonly(r))
        if not isinstance(self.unit, str) or not self.unit:
            raise ValueError(f"Scene.unit: expected a non-empty string, got {self.unit!r}")
        h, w = r.shape
        if self.rois is not None:
            rois: dict[int, Roi] = {}
            for k, roi in self.rois.items():
                y0, y1, x0, x1 = (int(v) for v in roi)
                if not (0 <= y0 < y1 <= h and 0 <= x0 < x1 <= w):
                    raise ValueError(
                        f"Scene.rois[{k}]: (y0, y1, x0, x1) = {tuple(roi)} is empty or outside "
                        f"the {w}x{h} (width x height) map"
                    )
                rois[int(k)] = (y0, y1, x0, x1)
            object.__setattr__(self, "rois", MappingProxyType(rois))
        if self.truth is not None:
            t = np.asarray(self.truth, dtype=np.float64)
            if t.ndim != 1:
                raise ValueError(f"Scene.truth: expected a 1-D array, got shape {t.shape}")
            if self.rois is not None and set(self.rois) != set(range(t.size)):
                raise ValueError(
                    f"Scene.truth: {t.size} values but rois are indexed "
                    f"{sorted(self.rois)[:5]}...; expected indices 0..{t.size - 1}"
                )
            object.__setattr__(self, "truth", _readonly(t))
        if self.densities is not None:
            d = np.asarray(self.densities, dtype=np.float64)
            if d.ndim != 1:
                raise ValueError(f"Scene.densities: expected a 1-D array, got shape {d.shape}")
            if self.truth is not None and d.size != self.truth.size:
                raise ValueError(
                    f"Scene.densities: {d.size} values but truth has {self.truth.size}"
                )
            object.__setattr__(self, "densities", _readonly(d))

    @property
    def width(self) -> int:
        """Width of the map, in pixels."""
        return int(self.radiance.shape[1])

    @property
    def height(self) -> int:
        """Height of the map, in pixels."""
        return int(self.radiance.shape[0])


def _check_finite_nonnegative(r: np.ndarray, what: str) -> None:
    bad = ~np.isfinite(r)
    if bad.any():
        n_nan = int(np.isnan(r).sum())
        raise ValueError(
            f"{what}: {int(bad.sum())} non-finite values ({n_nan} NaN, "
            f"{int(bad.sum()) - n_nan} infinite); radiance must be finite"
        )
    neg = r < 0
    if neg.any():
        raise ValueError(
            f"{what}: {int(neg.sum())} negative values (min {float(r.min()):.6g}); radiance "
            "must be non-negative: clip them when loading (asynhdr.io.images.read_radiance "
            "clips and counts them)"
        )


def _roi_margin_px(size_px: int, roi_margin: float) -> int:
    # ceil: with roi_margin > 0 the ROI never touches the patch's edge.
    return math.ceil(roi_margin * size_px - 1e-9)


def _min_patch_px(roi_margin: float) -> int:
    p = 1
    while p - 2 * _roi_margin_px(p, roi_margin) < _MIN_ROI_PX:
        p += 1
    return p


def step_chart(
    *,
    width: int,
    height: int,
    densities: npt.ArrayLike = PAPER_DENSITIES,
    illuminance_lux: float = PAPER_ILLUMINANCE_LUX,
    columns: int = 9,
    guard_px: int | None = None,
    roi_margin: float = 0.2,
    background_density: float | None = None,
) -> Scene:
    """A neutral-density step chart on a light box, as seen by a ``width`` x ``height`` sensor.

    Patch ``i`` (chart level ``i + 1``) has density ``D_i = densities[i]`` and radiance

        ``L_i = illuminance_lux * 10**(-D_i)``   [lux]

    (Wu et al. 2024, section on the step-chart experiment). Patches lie on a grid of
    ``columns`` columns and ``rows = ceil(n / columns)`` rows, row-major in level
    order (level 1 top-left). Between patches, and around the grid, are guard bands
    of ``guard_px`` pixels; the pixels left over by integer division widen the
    outer border, so the grid is centred.

    Background (guard bands, border and unused grid cells): the opaque frame of a
    real chart transmits almost nothing, but a frame of exactly zero radiance is a
    degenerate input for a log-domain sensor model. The default
    ``background_density`` is therefore ``max(densities) + 1``, one decade darker
    than the darkest patch (``illuminance_lux * 10**-9.22`` lux for the paper's
    chart). Pass ``math.inf`` for a true zero.

    Parameters
    ----------
    width, height:
        Sensor size, in pixels.
    densities:
        Optical densities, one per patch, non-negative (default: the paper's 36).
    illuminance_lux:
        Illuminance of the light box, in lux (default 160,000).
    columns:
        Patches per row.
    guard_px:
        Guard band between patches and around the grid, in pixels (default
        ``max(1, pitch // 10)`` with ``pitch = min(width // columns, height // rows)``).
    roi_margin:
        Fraction of the patch size (per axis, rounded up to whole pixels) left out on
        each side of the patch's region of interest, ``0 <= roi_margin < 0.5``.
    background_density:
        Density of the background (see above).

    Returns
    -------
    Scene
        ``unit="lux"``, ``name="step_chart"``, ``rois``, ``truth`` (``L_i``) and
        ``densities``.

    Raises
    ------
    ValueError
        If the sensor is too small for the grid (the message gives the minimum size)
        or an argument is out of range.
    """
    d = np.asarray(densities, dtype=np.float64)
    if d.ndim != 1 or d.size == 0:
        raise ValueError(f"step_chart: densities must be a non-empty 1-D list, got shape {d.shape}")
    if not np.all(np.isfinite(d)) or np.any(d < 0):
        raise ValueError("step_chart: densities must be finite and non-negative")
    if not (math.isfinite(illuminance_lux) and illuminance_lux > 0):
        raise ValueError(f"step_chart: illuminance_lux must be > 0, got {illuminance_lux}")
    if columns < 1:
        raise ValueError(f"step_chart: columns must be >= 1, got {columns}")
    if not (0.0 <= roi_margin < 0.5):
        raise ValueError(f"step_chart: roi_margin must be in [0, 0.5), got {roi_margin}")
    if guard_px is not None and guard_px < 0:
        raise ValueError(f"step_chart: guard_px must be >= 0, got {guard_px}")
    bg_density = float(d.max()) + 1.0 if background_density is None else float(background_density)
    if math.isnan(bg_density) or bg_density < 0:
        raise ValueError(
            f"step_chart: background_density must be >= 0 (inf for black), got {bg_density}"
        )

    n = int(d.size)
    cols = min(columns, n)
    rows = math.ceil(n / cols)
    p_min = _min_patch_px(roi_margin)
    g_min = 1 if guard_px is None else guard_px
    min_w = cols * p_min + (cols + 1) * g_min
    min_h = rows * p_min + (rows + 1) * g_min
    if width < min_w or height < min_h:
        raise ValueError(
            f"step_chart: a {width}x{height} (width x height) sensor is too small for "
            f"{n} patches in {rows} rows x {cols} columns: the minimum is {min_w}x{min_h} "
            f"(patches of {p_min} px with roi_margin={roi_margin}, guard bands of {g_min} px)"
        )
    if guard_px is None:
        guard_px = max(1, min(width // cols, height // rows) // 10)
    patch_w = (width - (cols + 1) * guard_px) // cols
    patch_h = (height - (rows + 1) * guard_px) // rows
    off_x = (width - cols * patch_w - (cols - 1) * guard_px) // 2
    off_y = (height - rows * patch_h - (rows - 1) * guard_px) // 2

    truth = np.array([illuminance_lux * 10.0 ** (-float(di)) for di in d], dtype=np.float64)
    background = illuminance_lux * 10.0 ** (-bg_density)
    radiance = np.full((height, width), background, dtype=np.float32)
    my = _roi_margin_px(patch_h, roi_margin)
    mx = _roi_margin_px(patch_w, roi_margin)
    rois: dict[int, Roi] = {}
    for i in range(n):
        r, c = divmod(i, cols)
        y0 = off_y + r * (patch_h + guard_px)
        x0 = off_x + c * (patch_w + guard_px)
        radiance[y0 : y0 + patch_h, x0 : x0 + patch_w] = np.float32(truth[i])
        rois[i] = (y0 + my, y0 + patch_h - my, x0 + mx, x0 + patch_w - mx)
    return Scene(
        radiance=radiance, unit="lux", name="step_chart", rois=rois, truth=truth, densities=d
    )


def flat_field(*, width: int, height: int, radiance: float, unit: str = "relative") -> Scene:
    """A uniform field ``L(y, x) = radiance`` over a ``width`` x ``height`` sensor.

    The whole frame is one patch (index 0, ROI = the frame) whose true radiance is
    ``radiance``, in ``unit``.
    """
    if width < 1 or height < 1:
        raise ValueError(f"flat_field: width and height must be >= 1, got {width}x{height}")
    if not (math.isfinite(radiance) and radiance >= 0):
        raise ValueError(f"flat_field: radiance must be finite and >= 0, got {radiance}")
    return Scene(
        radiance=np.full((height, width), radiance, dtype=np.float32),
        unit=unit,
        name="flat_field",
        rois={0: (0, height, 0, width)},
        truth=np.array([float(radiance)]),
    )


def _center_crop_to_aspect(a: np.ndarray, width: int, height: int) -> np.ndarray:
    h, w = a.shape
    if w * height > h * width:  # too wide
        new_w = max(1, round(h * width / height))
        x0 = (w - new_w) // 2
        return a[:, x0 : x0 + new_w]
    new_h = max(1, round(w * height / width))
    y0 = (h - new_h) // 2
    return a[y0 : y0 + new_h, :]


def _fit_size(h: int, w: int, width: int, height: int) -> tuple[int, int]:
    """Largest (rows, cols) with the map's aspect that fits in the sensor."""
    if w * height >= h * width:  # wider than the sensor: full width
        return max(1, round(h * width / w)), width
    return height, max(1, round(w * height / h))


def from_radiance_map(
    radiance: npt.ArrayLike,
    *,
    width: int,
    height: int,
    scale: float = 1.0,
    unit: str = "relative",
    name: str = "",
    fit: str = "pad",
    pad_radiance: float = 0.0,
) -> Scene:
    """A scene from a linear luminance map, resized to the sensor and scaled.

    ``L_out = scale * resize(L_in)``. Downscaling averages over pixel areas
    (``cv2.INTER_AREA``), which keeps the map linear and preserves its mean;
    upscaling interpolates bilinearly (``cv2.INTER_LINEAR``), which creates no
    negative values. Both run in float32 on the linear values (no gamma).

    Parameters
    ----------
    radiance:
        2-D linear luminance map ``(rows, cols)``, finite, non-negative.
    width, height:
        Sensor size, in pixels.
    scale:
        Factor applied after resizing (``> 0``), e.g. to set absolute units
        (:func:`exposure_scale`).
    unit, name:
        Stored in the :class:`Scene`.
    fit:
        ``"pad"`` (default) resizes the whole map to the largest size with its own
        aspect ratio that fits the sensor and centres it, the rest of the sensor at
        ``pad_radiance`` (an opaque surround); ``"crop"`` first crops the centre of the
        map to the sensor's aspect ratio; ``"stretch"`` resizes to exactly ``width`` x
        ``height`` whatever the aspect ratio (distorts).
    pad_radiance:
        Radiance of the padding (in ``unit``, after ``scale``).

    Returns
    -------
    Scene
        With ``rois={0: (y0, y1, x0, x1)}``: where the map lies on the sensor (the whole
        sensor unless padded).

    Raises
    ------
    ValueError
        Not 2-D, NaN or infinite values (with their count), negative values (with
        their count: clip them when loading), bad size, scale or fit.
    """
    a = np.asarray(radiance)
    if a.ndim != 2:
        raise ValueError(
            f"from_radiance_map: expected a 2-D (height, width) luminance map, got shape "
            f"{a.shape}; convert RGB with asynhdr.scene.luminance"
        )
    if a.size == 0:
        raise ValueError(f"from_radiance_map: empty map of shape {a.shape}")
    if width < 1 or height < 1:
        raise ValueError(f"from_radiance_map: width and height must be >= 1, got {width}x{height}")
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"from_radiance_map: scale must be finite and > 0, got {scale}")
    if fit not in ("stretch", "crop", "pad"):
        raise ValueError(
            f"from_radiance_map: fit must be 'pad', 'crop' or 'stretch', got {fit!r}")
    if not (math.isfinite(pad_radiance) and pad_radiance >= 0):
        raise ValueError(f"from_radiance_map: pad_radiance must be >= 0, got {pad_radiance}")
    a = a.astype(np.float32, copy=False)
    _check_finite_nonnegative(a, "from_radiance_map: radiance")
    if fit == "crop":
        a = _center_crop_to_aspect(a, width, height)
    h, w = a.shape
    rows, cols = (height, width) if fit != "pad" else _fit_size(h, w, width, height)
    if (h, w) == (rows, cols):
        inner = a.copy()
    else:
        interp = cv2.INTER_AREA if (cols <= w and rows <= h) else cv2.INTER_LINEAR
        inner = cv2.resize(np.ascontiguousarray(a), (cols, rows), interpolation=interp)
    inner = (inner.astype(np.float64) * scale).astype(np.float32)
    if not np.all(np.isfinite(inner)):
        raise ValueError(
            f"from_radiance_map: scale={scale} overflows float32 "
            f"(max input {float(a.max()):.6g})"
        )
    y0, x0 = (height - rows) // 2, (width - cols) // 2
    out = np.full((height, width), pad_radiance, dtype=np.float32)
    out[y0:y0 + rows, x0:x0 + cols] = np.maximum(inner, 0.0)
    return Scene(radiance=out, unit=unit, name=name,
                 rois={0: (y0, y0 + rows, x0, x0 + cols)})


def log_average(radiance: npt.ArrayLike, *, floor_fraction: float = 1e-6) -> float:
    """The log-average (geometric mean) ``exp(mean(ln max(L, f L_max)))`` of the
    positive part of a map, ``f = floor_fraction`` keeping black pixels from dragging it
    to zero (Reinhard et al. 2002's "key" of a scene uses the same average)."""
    a = np.asarray(radiance, dtype=np.float64)
    pos = a[a > 0]
    if pos.size == 0:
        raise ValueError("log_average: the map has no positive value")
    return float(np.exp(np.mean(np.log(np.maximum(pos, floor_fraction * pos.max())))))


def exposure_scale(radiance: npt.ArrayLike, *, target: float) -> float:
    """Automatic exposure: the factor that puts the scene's log-average at ``target``.

    ``s = target / log_average(L)``. HDR files hold relative values (or absolute
    values of another scene); multiplied by ``s`` they become the illuminance the rig
    sees (lux), with the scene's middle at ``target``: for a rig, the middle of its
    working range, :meth:`asynhdr.rig.Rig.mid_radiance`.
    """
    if not (math.isfinite(target) and target > 0):
        raise ValueError(f"exposure_scale: target must be > 0, got {target}")
    return target / log_average(radiance)


def luminance(rgb: npt.ArrayLike) -> np.ndarray:
    """Relative luminance of linear RGB with Rec. 709 / sRGB primaries.

    ``Y = 0.2126 R + 0.7152 G + 0.0722 B`` (ITU-R BT.709), over the last axis, which
    must have length 3 (drop alpha first). Computed in float64, returned as float32
    with the leading shape of ``rgb``.
    """
    a = np.asarray(rgb)
    if a.ndim < 1 or a.shape[-1] != 3:
        raise ValueError(
            f"luminance: expected (..., 3) linear RGB, got shape {a.shape}"
            + ("; drop the alpha channel first" if a.ndim >= 1 and a.shape[-1] == 4 else "")
        )
    a = a.astype(np.float64, copy=False)
    r, g, b = REC709_LUMA
    y = r * a[..., 0] + g * a[..., 1] + b * a[..., 2]
    return y.astype(np.float32)


@dataclass(frozen=True, eq=False)
class MovingScene:
    """A scene that moves: radiance frames and their times.

    Attributes
    ----------
    frames : float32 ``(n_frames, height, width)`` radiance; the simulator interpolates
        linearly in time between frames (``simulate(..., frame_times_us=times_us,
        engine="stepped")``).
    times_us : float64 ``(n_frames,)``, increasing.
    velocity_px_per_s : ``(vx, vy)``: how fast the content moves across the sensor.
    unit, name : as :class:`Scene`.
    """

    frames: np.ndarray
    times_us: np.ndarray
    velocity_px_per_s: tuple[float, float]
    unit: str = "relative"
    name: str = ""

    @property
    def radiance(self) -> np.ndarray:
        """The frames (what ``simulate`` takes as a moving scene)."""
        return self.frames

    @property
    def metadata(self) -> dict[str, object]:
        """What a recording of this scene should carry."""
        return {"motion": {"velocity_px_per_s": list(self.velocity_px_per_s),
                           "frame_step_us": float(np.median(np.diff(self.times_us)))
                           if self.times_us.size > 1 else None,
                           "n_frames": int(self.times_us.size)}}

    def at(self, t_us: float) -> np.ndarray:
        """The radiance at ``t_us`` (linear between frames, held outside them)."""
        t = self.times_us
        if t_us <= t[0]:
            return self.frames[0].astype(np.float64)
        if t_us >= t[-1]:
            return self.frames[-1].astype(np.float64)
        i = int(np.searchsorted(t, t_us, side="right")) - 1
        w = (t_us - t[i]) / (t[i + 1] - t[i])
        return (1.0 - w) * self.frames[i] + w * self.frames[i + 1].astype(np.float64)


def moving_scene(
    radiance: npt.ArrayLike,
    *,
    velocity_px_per_s: tuple[float, float],
    duration_us: float,
    frame_step_us: float = 1_000.0,
    t0_us: float = 0.0,
    unit: str = "relative",
    name: str = "",
) -> MovingScene:
    """An image moved across the sensor at a constant velocity: a pan.

    Frame ``n`` at ``t_n = t0 + n frame_step`` shows ``radiance`` shifted by
    ``v (t_n - t0)`` pixels (``v = (vx, vy)`` in px/s; content moves towards +x for
    ``vx > 0``), sampled by bilinear interpolation at sub-pixel offsets; what enters from
    outside the image repeats its edge. Frames cover ``[t0, t0 + duration]``; between them
    the simulator interpolates linearly, so a frame step well under the time an edge takes
    to cross a pixel (``1e6 / |v|`` µs) keeps edges sharp.
    """
    from scipy.ndimage import map_coordinates

    r = np.asarray(radiance, dtype=np.float64)
    if r.ndim != 2:
        raise ValueError(f"moving_scene: expected a 2-D (height, width) radiance, got shape "
                         f"{r.shape}")
    _check_finite_nonnegative(r, "moving_scene: radiance")
    vx, vy = (float(v) for v in velocity_px_per_s)
    if not (math.isfinite(vx) and math.isfinite(vy)):
        raise ValueError(f"moving_scene: velocity_px_per_s must be finite, got "
                         f"{velocity_px_per_s}")
    if not (duration_us > 0 and frame_step_us > 0 and math.isfinite(duration_us)):
        raise ValueError("moving_scene: duration_us and frame_step_us must be positive")
    n = math.ceil(duration_us / frame_step_us - 1e-9) + 1
    times = float(t0_us) + np.arange(n, dtype=np.float64) * frame_step_us
    h, w = r.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    frames = np.empty((n, h, w), dtype=np.float32)
    for i, t in enumerate(times):
        dt_s = (t - times[0]) * 1e-6
        frames[i] = map_coordinates(r, [yy - vy * dt_s, xx - vx * dt_s], order=1,
                                    mode="nearest")
    return MovingScene(frames=frames, times_us=times, velocity_px_per_s=(vx, vy), unit=unit,
                       name=name)
