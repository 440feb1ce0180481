"""Calibration files (``.npz``): per-pixel thresholds, the response, the panels' curves,
and a JSON record of how they were made.

Arrays (each optional): ``c_on``, ``c_off``, ``sigma_on``, ``sigma_off`` (float32
``(height, width)``, log units); ``defects`` (uint8 ``(height, width)``, 1 for a dead
pixel); ``response_x``, ``response_y`` (``ln`` of estimated and
true radiance); ``panel1_v``, ``panel1_t``, ``panel2_v``, ``panel2_t`` (the fitted static
curves: voltage in V, transmittance). Strings: ``format`` (``"asynhdr-calibration"``),
``version`` (1), ``how`` (JSON: inputs, radiances, counts, stated errors), ``sensor``
(JSON of the pixel model, or ``"null"``).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from asynhdr._atomic import atomic_path
from asynhdr.calib import Calibration, Response
from asynhdr.panel import PanelCurve
from asynhdr.sensor.params import SensorParams

__all__ = ["FORMAT", "read_calibration", "write_calibration"]

FORMAT = "asynhdr-calibration"
VERSION = 1


def write_calibration(path: str | os.PathLike[str], cal: Calibration) -> Path:
    """Write ``cal`` to ``path`` (``.npz``, atomically)."""
    p = Path(path)
    if p.suffix.lower() != ".npz":
        raise ValueError(f"{p}: a calibration file is written as .npz")
    arrays: dict[str, Any] = {
        "format": np.array(FORMAT), "version": np.array(VERSION),
        "how": np.array(json.dumps(cal.how, default=str)),
        "sensor": np.array(json.dumps(cal.sensor.to_metadata() if cal.sensor else None)),
    }
    for name in ("c_on", "c_off", "sigma_on", "sigma_off"):
        a = getattr(cal, name)
        if a is not None:
            arrays[name] = np.asarray(a, dtype=np.float32)
    if cal.defects is not None:
        arrays["defects"] = np.asarray(cal.defects, dtype=np.uint8)
    if cal.response is not None:
        arrays["response_x"] = cal.response.x
        arrays["response_y"] = cal.response.y
    for k, curve in cal.panel_curves.items():
        arrays[f"panel{k}_v"] = curve.voltages_v
        arrays[f"panel{k}_t"] = curve.transmittances
    with atomic_path(p) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)
    return p


def read_calibration(path: str | os.PathLike[str]) -> Calibration:
    """Read a calibration file; ``ValueError`` naming the file and what is wrong."""
    p = Path(path)
    try:
        z = np.load(p, allow_pickle=False)
    except FileNotFoundError:
        raise FileNotFoundError(f"{p}: calibration file not found") from None
    except (ValueError, OSError) as exc:
        raise ValueError(f"{p}: not a calibration file (.npz): {exc}") from None
    with z:
        if "format" not in z or str(z["format"]) != FORMAT:
            raise ValueError(f"{p}: 'format' must be {FORMAT!r} (is it a c-map? those are "
                             "given with --cmap)")
        if int(z["version"]) != VERSION:
            raise ValueError(f"{p}: version {int(z['version'])} is not {VERSION}")
        get = {k: z[k] for k in z.files}
    shape = None
    out: dict[str, np.ndarray | None] = {}
    for name in ("c_on", "c_off", "sigma_on", "sigma_off"):
        a = get.get(name)
        if a is not None:
            if a.ndim != 2:
                raise ValueError(f"{p}: {name} must be (height, width), got {a.shape}")
            if shape is not None and a.shape != shape:
                raise ValueError(f"{p}: {name} is {a.shape}, the other maps {shape}")
            shape = a.shape
            if not np.all(np.isfinite(a)) or (name.startswith("c_") and np.any(a <= 0)):
                raise ValueError(f"{p}: {name} must be finite (and thresholds positive)")
        out[name] = a
    defects = None
    if "defects" in get:
        d = get["defects"]
        if d.ndim != 2 or (shape is not None and d.shape != shape):
            raise ValueError(f"{p}: defects must be (height, width) like the threshold maps "
                             f"{shape}, got {d.shape}")
        if not np.isin(d, (0, 1)).all():
            raise ValueError(f"{p}: defects must hold 0 (working) or 1 (dead)")
        defects = d.astype(bool)
    resp = None
    if "response_x" in get and "response_y" in get:
        resp = Response(np.asarray(get["response_x"], np.float64),
                        np.asarray(get["response_y"], np.float64))
    curves = {}
    for k in ("1", "2"):
        if f"panel{k}_v" in get:
            curves[k] = PanelCurve(get[f"panel{k}_v"], get[f"panel{k}_t"],
                                   name=f"panel {k} from a sweep")
    sensor_d = json.loads(str(get["sensor"])) if "sensor" in get else None
    sensor = SensorParams.from_metadata(sensor_d) if isinstance(sensor_d, dict) else None
    how = json.loads(str(get["how"])) if "how" in get else {}
    return Calibration(c_on=out["c_on"], c_off=out["c_off"], sigma_on=out["sigma_on"],
                       sigma_off=out["sigma_off"], defects=defects, response=resp,
                       panel_curves=curves, sensor=sensor, how=how)
