"""Rig files: a real (or simulated) rig described in TOML, so that radiometric methods
(``ml``, ``invert``, ``ttfe``) run on recordings whose files do not carry the rig.

The format (``format = "asynhdr-rig"``, ``version = 1``)::

    format = "asynhdr-rig"
    version = 1

    [rig]                       # asynhdr.rig.Rig's fields, units in their names
    period_us = 50000           # cycle length (µs); cycles start at the trigger edges
    ramp_fraction = 0.9         # the part of the cycle that is integrated
    l_const = 300.0             # reference radiance, in radiance_unit
    k_lens = 1.0                # lens attenuation (both paths)
    radiance_unit = "lux"       # the unit of l_const, and of the images
    t1_shape = "exponential"    # generated ramps: linear | exponential ...
    t2_shape = "exponential"
    t2_stop = 1.0
    contrast_ratio_1 = 1000.0
    contrast_ratio_2 = 1000.0
    panel = "ideal"             # ideal | tn | fast_shutter: the drive goes through these
    pre_emphasis = true
    sample_rate_hz = 1000000.0
    design_range = [0.1, 316227.8]  # optional: the scene radiances it was designed for

    [rig.t1]                    # optional: the TRANSMITTED waveform, measured or designed
    phase = [0.0, ..., 1.0]     # fraction of the period, 0 to 1, increasing
    values = [0.001, ..., 1.0]  # transmittance at those phases, in [0, 1]

    [sensor]                    # optional: the pixel model (asynhdr.sensor.params)
    preset = "imx636"           # start from a preset ...
    refractory_us = 100.0       # ... and change fields

    [made]                      # how the file was made (free form)
    by = "asynhdr design"

Every key of ``[rig]`` but ``period_us`` and ``l_const`` has the default of
:class:`asynhdr.rig.Rig`. Unknown keys are an error that names the file and the key. The
file is written by ``asynhdr simulate --rig-out`` and ``asynhdr design``, and read by
``asynhdr reconstruct --rig``.
"""

from __future__ import annotations

import math
import os
import sys
from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np

from asynhdr._atomic import atomic_path
from asynhdr.rig import Rig
from asynhdr.sensor.params import SensorParams, get_preset
from asynhdr.transmittance import Waveform

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = ["FORMAT", "VERSION", "RigFile", "read_rig", "rig_toml", "write_rig"]

FORMAT = "asynhdr-rig"
VERSION = 1

_RIG_KEYS = ("period_us", "ramp_fraction", "t1_shape", "t2_shape", "contrast_ratio_1",
             "contrast_ratio_2", "t2_stop", "l_const", "k_lens", "n_knots", "panel",
             "pre_emphasis", "sample_rate_hz", "design_range")


class RigFile:
    """What a rig file holds: the rig, the sensor model (or None), the radiance unit and
    the ``[made]`` record."""

    def __init__(self, rig: Rig, sensor: SensorParams | None, radiance_unit: str,
                 made: dict[str, Any]) -> None:
        self.rig = rig
        self.sensor = sensor
        self.radiance_unit = radiance_unit
        self.made = made


# ----------------------------------------------------------------------------- writing


def _value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | np.integer):
        return str(int(v))
    if isinstance(v, float | np.floating):
        f = float(v)
        if math.isnan(f):
            return "nan"
        if math.isinf(f):
            return "inf" if f > 0 else "-inf"
        return repr(f)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'
    if isinstance(v, list | tuple | np.ndarray):
        items = [_value(x) for x in v]
        lines, line = [], ""
        for it in items:
            if len(line) + len(it) > 96:
                lines.append(line)
                line = ""
            line += it + ", "
        lines.append(line)
        if len(lines) == 1:
            return "[" + lines[0].rstrip(", ") + "]"
        return "[\n    " + "\n    ".join(x.rstrip() for x in lines if x) + "\n]"
    raise TypeError(f"rig file: cannot write a value of type {type(v).__name__}")


def _table(name: str, d: dict[str, Any], comments: dict[str, str] | None = None) -> str:
    out = [f"[{name}]"]
    for k, v in d.items():
        if v is None or isinstance(v, dict):
            continue
        line = f"{k} = {_value(v)}"
        if comments and k in comments:
            line += f"  # {comments[k]}"
        out.append(line)
    return "\n".join(out) + "\n"


_COMMENTS = {
    "period_us": "cycle length (µs); cycles start at the trigger edges",
    "ramp_fraction": "part of the cycle that is integrated",
    "l_const": "reference radiance, in radiance_unit",
    "k_lens": "lens attenuation (both paths)",
    "panel": "ideal | tn | fast_shutter",
    "design_range": "scene radiances designed for (automatic exposure centres on them)",
}


def rig_toml(rig: Rig, *, sensor: SensorParams | None = None, radiance_unit: str = "lux",
             made: dict[str, Any] | None = None) -> str:
    """The TOML text of a rig file (module docstring). Waveforms given to the rig as
    samples, or transmitted through real panels, are written as ``[rig.t1]`` and
    ``[rig.t2]`` tables of the *transmitted* transmittance."""
    meta = rig.to_metadata()
    rig_d = {k: meta[k] for k in _RIG_KEYS if k in meta}
    sampled = rig.t1 is not None or rig.t2 is not None or rig.panel != "ideal"
    if sampled and rig.design_range is None:
        # read back, the rig is its transmitted waveforms, whose extremes (a real panel's
        # leakage and slow opening) would set another working range: keep this one
        rig_d["design_range"] = list(rig.working_range())
    rig_d["radiance_unit"] = radiance_unit
    parts = [f'format = "{FORMAT}"\nversion = {VERSION}\n', _table("rig", rig_d, _COMMENTS)]
    if sampled:
        w1, w2 = rig.waveforms()
        for name, w in (("t1", w1), ("t2", w2)):
            parts.append(_table(f"rig.{name}", {"name": w.name, "phase": w.phase.tolist(),
                                                "values": w.values.tolist()}))
    if sensor is not None:
        sd = sensor.to_metadata()
        base = sensor.name if sensor.name in _preset_names() else None
        out: dict[str, Any] = {}
        if base is not None:
            out["preset"] = base
            ref = get_preset(base).to_metadata()
            out.update({k: v for k, v in sd.items() if k != "name" and ref.get(k) != v})
        else:
            out.update({k: v for k, v in sd.items() if k != "name"})
        parts.append(_table("sensor", out))
    if made:
        parts.append(_table("made", {k: (v if isinstance(v, str | int | float | bool)
                                          else str(v)) for k, v in made.items()}))
    return "\n".join(parts)


def _preset_names() -> tuple[str, ...]:
    from asynhdr.sensor.params import PRESETS

    return tuple(PRESETS)


def write_rig(path: str | os.PathLike[str], rig: Rig, *, sensor: SensorParams | None = None,
              radiance_unit: str = "lux", made: dict[str, Any] | None = None) -> Path:
    """Write a rig file (atomically); returns its path."""
    p = Path(path)
    text = rig_toml(rig, sensor=sensor, radiance_unit=radiance_unit, made=made)
    with atomic_path(p) as tmp:
        Path(tmp).write_text(text, encoding="utf-8")
    return p


# ----------------------------------------------------------------------------- reading


def _bad(path: Path, where: str, msg: str) -> ValueError:
    return ValueError(f"{path}: {where}: {msg}")


def read_rig(path: str | os.PathLike[str]) -> RigFile:
    """Read a rig file; ``ValueError`` naming the file and the field for anything wrong."""
    p = Path(path)
    try:
        doc = tomllib.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise FileNotFoundError(f"{p}: rig file not found") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{p}: not a TOML rig file: {exc}") from None
    if doc.get("format") != FORMAT:
        raise _bad(p, "format", f'expected "{FORMAT}", got {doc.get("format")!r}')
    if doc.get("version") != VERSION:
        raise _bad(p, "version", f"expected {VERSION}, got {doc.get('version')!r}")
    unknown = set(doc) - {"format", "version", "rig", "sensor", "made"}
    if unknown:
        raise _bad(p, "top level", f"unknown keys {sorted(unknown)}")
    rd = doc.get("rig")
    if not isinstance(rd, dict):
        raise _bad(p, "[rig]", "missing")
    for req in ("period_us", "l_const"):
        if req not in rd:
            raise _bad(p, f"rig.{req}", "missing")
    allowed = {*_RIG_KEYS, "radiance_unit", "t1", "t2"}
    extra = set(rd) - allowed
    if extra:
        raise _bad(p, "[rig]", f"unknown keys {sorted(extra)}; expected some of "
                   f"{sorted(allowed)}")
    kw: dict[str, Any] = {k: rd[k] for k in _RIG_KEYS if k in rd}
    if "design_range" in kw:
        dr = kw["design_range"]
        if not isinstance(dr, list) or len(dr) != 2:
            raise _bad(p, "rig.design_range", f"expected [lowest, highest], got {dr!r}")
        kw["design_range"] = tuple(dr)
    for name in ("t1", "t2"):
        if name in rd:
            w = rd[name]
            if not isinstance(w, dict) or "phase" not in w or "values" not in w:
                raise _bad(p, f"rig.{name}", "expected a table with 'phase' and 'values'")
            try:
                kw[name] = Waveform(np.asarray(w["phase"], dtype=np.float64),
                                    np.asarray(w["values"], dtype=np.float64),
                                    name=str(w.get("name", "from rig file")))
            except (ValueError, TypeError) as exc:
                raise _bad(p, f"rig.{name}", str(exc)) from None
    if "panel" in kw and ("t1" in kw or "t2" in kw):
        kw["panel"] = "ideal"  # the tables are the transmitted waveforms already
    try:
        rig = Rig(**kw)
    except (ValueError, TypeError) as exc:
        raise _bad(p, "[rig]", str(exc)) from None
    unit = str(rd.get("radiance_unit", "relative"))
    sensor = None
    if "sensor" in doc:
        sd = dict(doc["sensor"])
        preset = sd.pop("preset", None)
        names = {f.name for f in fields(SensorParams)}
        bad_keys = set(sd) - names
        if bad_keys:
            raise _bad(p, "[sensor]", f"unknown keys {sorted(bad_keys)}")
        try:
            base = get_preset(str(preset)) if preset is not None else SensorParams()
            sensor = base.with_(name=base.name if not sd else f"{base.name}+file", **sd)
        except (ValueError, TypeError) as exc:
            raise _bad(p, "[sensor]", str(exc)) from None
    made = dict(doc.get("made", {}))
    return RigFile(rig, sensor, unit, made)
