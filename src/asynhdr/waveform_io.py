"""Waveform files for arbitrary-waveform generators: one file per panel, plus a sidecar.

A :class:`asynhdr.waveform.Design` holds one cycle of commanded voltage per panel at the
generator's sample rate. Generators and their PC tools import one channel per file, in
their own formats; :func:`write_waveform_files` writes, for each panel ``k`` (1 = scene
panel, 2 = reference panel):

``panel{k}.csv``
    a plain column of volts, one sample a line, no header: what every import tool that
    takes "a list of values" accepts, and the exact (``%.17g``) record of the design;
``panel{k}.arb``
    the Keysight 33500/33600 ``.arb`` text format (the format BenchLink Waveform Builder
    writes and the 33500B/33600A load from USB or ``MMEM:LOAD:DATA``): a header of
    ``Key:Value`` lines (``File Format:1.10``, ``Channel Count:1``, ``Sample Rate``,
    ``High Level``, ``Low Level``, ``Marker Point``, ``Data Type:"short"``,
    ``Filter:"off"``, ``Data Points``, ``Data:``) then one signed 16-bit sample a line,
    ``-32767`` at ``Low Level`` and ``+32767`` at ``High Level`` volts;
``panel{k}_sdg.csv``
    the Siglent EasyWave / SDG CSV layout (``data length``, ``frequency``, ``amp``,
    ``offset``, ``phase`` lines, seven ``,`` lines, ``xpos,value``, then ``time,volts``
    rows), which the SDG1000X/2000X/6000X recall from a USB stick as a user waveform;

and ``waveform.json``: the design's metadata (sample rate, period, carrier, panels, errors)
and, per panel, the file names, amplitude and offset, so that the files can be read back
(:func:`read_waveform_files`) and loaded into a generator (:mod:`asynhdr.generator`).

Amplitude and offset: a channel spanning ``[v_min, v_max]`` volts is played as amplitude
``A = v_max - v_min`` (peak to peak) around offset ``O = (v_max + v_min) / 2``; the
generator's normalised sample is ``s = (v - O) / (A / 2)`` in ``[-1, 1]``
(:func:`channel_scale`). All writes are atomic; readers raise ``ValueError`` naming the
file, the line and what was expected.

Sources: Keysight 33500 Series Operating and Service Guide, "Arbitrary waveforms" and
``MMEMory:LOAD:DATA`` (the ``.arb`` header keys); Siglent SDG series user manuals,
"Store/Recall" of ``.csv`` user waveforms (the EasyWave export layout). See
``docs/generator.md``.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from asynhdr._atomic import atomic_path

__all__ = [
    "ARB_FULL_SCALE",
    "SIDECAR_NAME",
    "ChannelScale",
    "WaveformFiles",
    "channel_scale",
    "read_arb",
    "read_column_csv",
    "read_siglent_csv",
    "read_waveform_files",
    "write_arb",
    "write_column_csv",
    "write_siglent_csv",
    "write_waveform_files",
]

SIDECAR_NAME = "waveform.json"
"""Name of the sidecar that :func:`write_waveform_files` writes beside the channel files."""

ARB_FULL_SCALE = 32767
"""Keysight ``.arb`` and 16-bit DAC full scale: ``+32767`` is the high level, ``-32767``
the low level (symmetric, so 0 is the offset)."""

MIN_AMPLITUDE_VPP = 1e-3
"""Amplitude given to a constant channel (generators refuse 0 Vpp; 1 mVpp is the usual
minimum of the 33500B, DG800 and SDG families)."""

_SIGLENT_BLANK_LINES = 7


@dataclass(frozen=True)
class ChannelScale:
    """How a generator plays one channel.

    Attributes
    ----------
    amplitude_vpp : ``A = v_max - v_min``, volts peak to peak.
    offset_v : ``O = (v_max + v_min) / 2``, volts.
    normalized : ``s = (v - O) / (A / 2)``, float64 in ``[-1, 1]``.
    """

    amplitude_vpp: float
    offset_v: float
    normalized: np.ndarray

    @property
    def high_v(self) -> float:
        """Voltage at ``s = +1``."""
        return self.offset_v + self.amplitude_vpp / 2.0

    @property
    def low_v(self) -> float:
        """Voltage at ``s = -1``."""
        return self.offset_v - self.amplitude_vpp / 2.0

    def codes(self, *, full_scale: int = ARB_FULL_SCALE) -> np.ndarray:
        """Signed integer codes ``round(s * full_scale)`` (int16 for the default)."""
        return np.round(self.normalized * full_scale).astype(np.int16)


def channel_scale(voltage_v: np.ndarray) -> ChannelScale:
    """Amplitude, offset and normalised samples of one channel (module docstring).

    A constant channel gets :data:`MIN_AMPLITUDE_VPP` around its value.
    """
    v = np.asarray(voltage_v, dtype=np.float64)
    if v.ndim != 1 or v.size < 2:
        raise ValueError(f"a channel needs a 1-D array of at least 2 samples, got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"a channel has {int((~np.isfinite(v)).sum())} non-finite samples")
    hi, lo = float(v.max()), float(v.min())
    amp = hi - lo
    off = (hi + lo) / 2.0
    if amp <= 0:
        return ChannelScale(MIN_AMPLITUDE_VPP, off, np.zeros_like(v))
    s = np.clip((v - off) / (amp / 2.0), -1.0, 1.0)
    return ChannelScale(amp, off, s)


# --------------------------------------------------------------------------- plain column

def write_column_csv(path: str | os.PathLike[str], voltage_v: np.ndarray) -> Path:
    """One sample a line, volts, ``%.17g`` (float64 round-trips exactly); atomic."""
    v = np.asarray(voltage_v, dtype=np.float64)
    target = Path(path)
    with atomic_path(target) as tmp:
        np.savetxt(tmp, v, fmt="%.17g", newline="\n")
    return target


def read_column_csv(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a one-column file of volts (float64); blank lines are skipped."""
    p = Path(path)
    values: list[float] = []
    with open(p, encoding="utf-8") as fh:
        for n, line in enumerate(fh, start=1):
            text = line.strip()
            if not text:
                continue
            try:
                values.append(float(text))
            except ValueError:
                raise ValueError(f"{p}: line {n}: expected one number (volts), found "
                                 f"{text[:40]!r}") from None
    if len(values) < 2:
        raise ValueError(f"{p}: expected at least 2 samples, found {len(values)}")
    return np.asarray(values, dtype=np.float64)


# --------------------------------------------------------------------------- Keysight .arb

def write_arb(path: str | os.PathLike[str], voltage_v: np.ndarray, *, sample_rate_hz: float,
              marker_point: int | None = None) -> Path:
    """Keysight 33500/33600 ``.arb`` text file of one channel (module docstring); atomic.

    ``marker_point`` (1-based sample where the Sync output falls; default the middle)
    sets the width of the Sync pulse that marks each cycle start.
    """
    sc = channel_scale(voltage_v)
    n = sc.normalized.size
    marker = n // 2 if marker_point is None else int(marker_point)
    if not 1 <= marker <= n:
        raise ValueError(f"marker_point must be in [1, {n}], got {marker}")
    head = [
        "Copyright:asynhdr",
        "File Format:1.10",
        "Channel Count:1",
        f"Sample Rate:{sample_rate_hz:.6f}",
        f"High Level:{sc.high_v:.9f}",
        f"Low Level:{sc.low_v:.9f}",
        f"Marker Point:{marker}",
        'Data Type:"short"',
        'Filter:"off"',
        f"Data Points:{n}",
        "Data:",
    ]
    codes = sc.codes()
    target = Path(path)
    with atomic_path(target) as tmp:
        with open(tmp, "w", encoding="ascii", newline="\r\n") as fh:
            fh.write("\n".join(head) + "\n")
            fh.write("\n".join(str(int(c)) for c in codes) + "\n")
    return target


def read_arb(path: str | os.PathLike[str]) -> tuple[np.ndarray, dict[str, Any]]:
    """Read a Keysight ``.arb`` text file: ``(volts, header)``.

    Volts are ``Low + (d + 32767) / 65534 * (High - Low)`` for ``Data Type:"short"``;
    ``header`` holds the ``Key:Value`` lines (numbers as float, quoted strings unquoted).
    """
    p = Path(path)
    header: dict[str, Any] = {}
    data: list[int] = []
    in_data = False
    with open(p, encoding="ascii", errors="replace") as fh:
        for n, line in enumerate(fh, start=1):
            text = line.strip()
            if not text:
                continue
            if in_data:
                try:
                    data.append(int(text))
                except ValueError:
                    raise ValueError(f"{p}: line {n}: expected an integer sample, found "
                                     f"{text[:40]!r}") from None
                continue
            if text == "Data:":
                in_data = True
                continue
            key, sep, val = text.partition(":")
            if not sep:
                raise ValueError(f"{p}: line {n}: expected a 'Key:Value' header line or "
                                 f"'Data:', found {text[:40]!r}")
            val = val.strip()
            try:
                header[key.strip()] = float(val)
            except ValueError:
                header[key.strip()] = val.strip('"')
    for key in ("Sample Rate", "High Level", "Low Level", "Data Points"):
        if not isinstance(header.get(key), float):
            raise ValueError(f"{p}: header field {key!r} missing or not a number")
    if str(header.get("Data Type", "short")).lower() != "short":
        raise ValueError(f"{p}: Data Type {header['Data Type']!r} not supported; expected "
                         "\"short\"")
    if not in_data:
        raise ValueError(f"{p}: no 'Data:' line")
    if len(data) != int(header["Data Points"]):
        raise ValueError(f"{p}: header says Data Points:{int(header['Data Points'])}, found "
                         f"{len(data)} samples")
    d = np.asarray(data, dtype=np.float64)
    if np.any(np.abs(d) > ARB_FULL_SCALE):
        raise ValueError(f"{p}: samples outside [-32767, 32767]")
    lo, hi = float(header["Low Level"]), float(header["High Level"])
    return lo + (d + ARB_FULL_SCALE) / (2 * ARB_FULL_SCALE) * (hi - lo), header


# --------------------------------------------------------------------------- Siglent CSV

def write_siglent_csv(path: str | os.PathLike[str], voltage_v: np.ndarray, *,
                      sample_rate_hz: float) -> Path:
    """Siglent EasyWave / SDG ``.csv`` of one channel (module docstring); atomic.

    ``frequency`` is the repetition rate ``sample_rate_hz / N``; ``amp`` and ``offset``
    are the channel's peak-to-peak amplitude and offset; rows are ``t_n,v_n``.
    """
    v = np.asarray(voltage_v, dtype=np.float64)
    sc = channel_scale(v)
    n = v.size
    t = np.arange(n, dtype=np.float64) / sample_rate_hz
    head = [f"data length,{n}", f"frequency,{sample_rate_hz / n:.9g}",
            f"amp,{sc.amplitude_vpp:.9g}", f"offset,{sc.offset_v:.9g}", "phase,0"]
    head += [","] * _SIGLENT_BLANK_LINES + ["xpos,value"]
    target = Path(path)
    with atomic_path(target) as tmp:
        with open(tmp, "w", encoding="ascii", newline="\n") as fh:
            fh.write("\n".join(head) + "\n")
            np.savetxt(fh, np.column_stack([t, v]), fmt=["%.9e", "%.17g"], delimiter=",")
    return target


def read_siglent_csv(path: str | os.PathLike[str]) -> tuple[np.ndarray, dict[str, Any]]:
    """Read a Siglent EasyWave ``.csv``: ``(volts, header)`` (header keys lower-case)."""
    p = Path(path)
    header: dict[str, Any] = {}
    values: list[float] = []
    in_data = False
    with open(p, encoding="utf-8", errors="replace") as fh:
        for n, line in enumerate(fh, start=1):
            text = line.strip()
            if not text:
                continue
            cells = [c.strip() for c in text.split(",")]
            if not in_data:
                if [c.lower() for c in cells[:2]] == ["xpos", "value"]:
                    in_data = True
                elif cells[0]:
                    try:
                        header[cells[0].lower()] = float(cells[1])
                    except (IndexError, ValueError):
                        raise ValueError(f"{p}: line {n}: expected 'key,number' in the header, "
                                         f"found {text[:40]!r}") from None
                continue
            if len(cells) < 2:
                raise ValueError(f"{p}: line {n}: expected 'xpos,value', found {text[:40]!r}")
            try:
                values.append(float(cells[1]))
            except ValueError:
                raise ValueError(f"{p}: line {n}: value {cells[1][:20]!r} is not a number"
                                 ) from None
    if not in_data:
        raise ValueError(f"{p}: no 'xpos,value' line; not a Siglent EasyWave CSV")
    if "data length" in header and int(header["data length"]) != len(values):
        raise ValueError(f"{p}: header says data length {int(header['data length'])}, found "
                         f"{len(values)} rows")
    return np.asarray(values, dtype=np.float64), header


# --------------------------------------------------------------------------- the set

@dataclass(frozen=True, eq=False)
class WaveformFiles:
    """A design read back from its files.

    Attributes
    ----------
    voltage_v : ``(panel 1, panel 2)`` commanded voltages over one cycle, float64.
    sample_rate_hz, period_us, carrier_hz : as designed (``carrier_hz`` None: DC).
    metadata : the sidecar's content (panels, errors, files, scales).
    """

    voltage_v: tuple[np.ndarray, np.ndarray]
    sample_rate_hz: float
    period_us: int
    carrier_hz: float | None
    metadata: dict[str, Any]

    @property
    def n_samples(self) -> int:
        """Samples per cycle."""
        return int(self.voltage_v[0].size)


def write_waveform_files(folder: str | os.PathLike[str], voltage_v: tuple[np.ndarray, np.ndarray],
                         *, sample_rate_hz: float, period_us: int,
                         metadata: dict[str, Any]) -> dict[str, Path]:
    """Write both panels in every format and the sidecar ``waveform.json`` into ``folder``.

    ``metadata`` (e.g. ``Design.to_metadata()``) goes into the sidecar with the file names
    and each channel's amplitude and offset. Returns ``{name: path}``; the sidecar is
    written last, so a folder with a sidecar has all its files.
    """
    out = Path(folder)
    written: dict[str, Path] = {}
    channels = []
    for k, v in enumerate(voltage_v, start=1):
        v = np.asarray(v, dtype=np.float64)
        sc = channel_scale(v)
        files = {"column_csv": f"panel{k}.csv", "keysight_arb": f"panel{k}.arb",
                 "siglent_csv": f"panel{k}_sdg.csv"}
        written[files["column_csv"]] = write_column_csv(out / files["column_csv"], v)
        written[files["keysight_arb"]] = write_arb(out / files["keysight_arb"], v,
                                                   sample_rate_hz=sample_rate_hz)
        written[files["siglent_csv"]] = write_siglent_csv(out / files["siglent_csv"], v,
                                                          sample_rate_hz=sample_rate_hz)
        channels.append({"panel": k, "files": files, "amplitude_vpp": sc.amplitude_vpp,
                         "offset_v": sc.offset_v, "n_samples": int(v.size)})
    side = dict(metadata)
    side.update({"format": "asynhdr waveform files", "format_version": 1,
                 "sample_rate_hz": float(sample_rate_hz), "period_us": int(period_us),
                 "channels": channels})
    path = out / SIDECAR_NAME
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(side, indent=1, default=_json_default) + "\n",
                       encoding="utf-8")
    written[SIDECAR_NAME] = path
    return written


def _json_default(o: object) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


def read_waveform_files(folder: str | os.PathLike[str]) -> WaveformFiles:
    """Read what :func:`write_waveform_files` wrote (the exact plain-column files).

    Raises
    ------
    FileNotFoundError : no sidecar in ``folder``.
    ValueError : a sidecar field missing or wrong, a channel file that does not match
        the sidecar's sample count.
    """
    base = Path(folder)
    side_path = base / SIDECAR_NAME if base.is_dir() or not base.suffix else base
    base = side_path.parent
    if not side_path.is_file():
        raise FileNotFoundError(f"{side_path}: no waveform sidecar; write one with "
                                "'asynhdr waveform --out DIR'")
    try:
        side = json.loads(side_path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise ValueError(f"{side_path}: not JSON ({exc})") from None
    for key, typ in (("sample_rate_hz", (int, float)), ("period_us", int),
                     ("channels", list)):
        if not isinstance(side.get(key), typ):
            raise ValueError(f"{side_path}: field {key!r} missing or not a "
                             f"{'list' if typ is list else 'number'}")
    if len(side["channels"]) != 2:
        raise ValueError(f"{side_path}: field 'channels' must list 2 panels, found "
                         f"{len(side['channels'])}")
    volts = []
    for ch in side["channels"]:
        try:
            name = ch["files"]["column_csv"]
            n = int(ch["n_samples"])
        except (KeyError, TypeError, ValueError):
            raise ValueError(f"{side_path}: channel entry {ch!r} lacks files.column_csv or "
                             "n_samples") from None
        v = read_column_csv(base / name)
        if v.size != n:
            raise ValueError(f"{base / name}: {v.size} samples, the sidecar says {n}")
        volts.append(v)
    carrier = side.get("carrier_hz")
    if carrier is not None and not (isinstance(carrier, (int, float)) and math.isfinite(carrier)):
        raise ValueError(f"{side_path}: field 'carrier_hz' must be a number or null")
    return WaveformFiles(voltage_v=(volts[0], volts[1]),
                         sample_rate_hz=float(side["sample_rate_hz"]),
                         period_us=int(side["period_us"]),
                         carrier_hz=None if carrier is None else float(carrier), metadata=side)
