"""What ``asynhdr reconstruct`` needs for rig files and for ``ml``'s extra outputs.

For ``--method ml`` each cycle writes, beside the radiance image (NaN where a pixel has no
information; the range's bound where the estimate reached it), ``<stem>_sigma.<ext>``:
the standard deviation of ``ln L`` per pixel (the likelihood's at the estimate), in the
first float format asked for (``.exr`` by default), and ``<stem>_valid.png``: 255 where
the pixel's events were fitted inside the model's range, 128 where its estimate comes
from fewer than two events (:data:`asynhdr.ml.FLAG_FEW_EVENTS`: every silent pixel of the
same thresholds reads the same, so a region's spread says nothing of their error; their
deviation in ``_sigma`` does) or from few events that other values explain about as well
(:data:`asynhdr.ml.FLAG_AMBIGUOUS`: a deviation of 1 or more), 0 where it has none. A
calibration file's dead pixels are filled from their neighbours (and are 0 in
``_valid.png``).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from asynhdr.rig import Rig
from asynhdr.sensor.params import SensorParams

__all__ = ["MlOutputs"]

_FLOAT_FORMATS = ("exr", "npy", "tif")


class MlOutputs:
    """The rig (and sensor) of a rig file, the calibration, and the writer of ``ml``'s
    images, uncertainty and mask."""

    def __init__(self, *, rig: Rig | None, sensor: SensorParams | None, unit: str | None,
                 thresholds: tuple[np.ndarray, np.ndarray, np.ndarray] | None, method: str,
                 formats: list[str], defects: np.ndarray | None = None) -> None:
        self.rig = rig
        self.sensor = sensor
        self.unit = unit
        self.thresholds = thresholds
        self.defects = defects
        self.filled = 0  # dead pixels filled in the last cycle written
        # the last cycle written: its pixels with an estimate, those of them from fewer
        # than two events, and all its pixels
        self.valid = 0
        self.few = 0
        self.pixels = 0
        self.full_fits: int | None = None  # with --fast: its pixels fitted in full
        self.active = method == "ml"
        self.formats = formats
        self.extra: dict[str, Any] = {}

    @classmethod
    def open(cls, rig_path: Path | None, calibration: Path | None, *, method: str,
             formats: list[str], fail: Callable[[str], None]) -> MlOutputs:
        rig = sensor = unit = thr = dead = None
        try:
            if rig_path is not None:
                from asynhdr.io.rigfile import read_rig

                rf = read_rig(rig_path)
                rig, sensor, unit = rf.rig, rf.sensor, rf.radiance_unit
            if calibration is not None:
                from asynhdr.io.calibration import read_calibration

                cal = read_calibration(calibration)
                thr = cal.threshold_maps()
                if thr is None:
                    fail(f"{calibration}: holds no per-pixel thresholds")
                dead = cal.defects
                if sensor is None and cal.sensor is not None:
                    sensor = cal.sensor
        except (ValueError, OSError) as exc:
            fail(str(exc))
        return cls(rig=rig, sensor=sensor, unit=unit, thresholds=thr, method=method,
                   formats=formats, defects=dead)

    @property
    def options(self) -> dict[str, Any] | None:
        """``ml_options`` for :func:`asynhdr.reconstruct.reconstruct`."""
        if not self.active:
            return None
        return {"sensor": self.sensor, "thresholds": self.thresholds,
                "defects": self.defects, "out": self.extra}

    def write(self, stem: Path, img: np.ndarray, meta: dict[str, Any], *,
              tonemap: str) -> None:
        from asynhdr.io.images import write_image

        for f in self.formats:
            write_image(Path(f"{stem}.{f}"), img, allow_nan=True, tonemap=tonemap,
                        metadata=meta if f in ("exr", "tif") else None)
        sigma = self.extra.get("sigma_log")
        flags = self.extra.get("flags")
        if sigma is None or flags is None:
            return
        fl = next((f for f in self.formats if f in _FLOAT_FORMATS), "exr")
        sm = dict(meta, quantity="standard deviation of ln L (the likelihood's at the "
                  "estimate, widened where it has more than one optimum)")
        write_image(Path(f"{stem}_sigma.{fl}"), sigma[0], allow_nan=True,
                    metadata=sm if fl in ("exr", "tif") else None)
        import cv2

        from asynhdr._atomic import atomic_path
        from asynhdr.ml import FLAG_FEW_EVENTS, FLAG_FILLED, valid_flags

        full = self.extra.get("full_fits")
        self.full_fits = None if full is None else int(full[0])
        self.filled = int(np.count_nonzero(flags[0] & FLAG_FILLED))
        ok = valid_flags(flags[0])
        self.valid = int(np.count_nonzero(ok))
        self.few = int(np.count_nonzero(flags[0] == FLAG_FEW_EVENTS))
        self.pixels = int(ok.size)
        valid = np.where(flags[0] == 0, 255, np.where(ok, 128, 0)).astype(np.uint8)
        with atomic_path(Path(f"{stem}_valid.png")) as tmp:
            if not cv2.imwrite(str(tmp), valid):
                raise OSError(f"{stem}_valid.png: OpenCV failed to write the mask")
