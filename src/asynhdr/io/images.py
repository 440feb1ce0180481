"""Image files: real HDR radiance maps in, reconstructed HDR images out.

Reading (:func:`read_radiance`) turns an HDR file into a linear float32 luminance
map ``(height, width)``:

==========  ===================================  ==============================
extension   library                              content
==========  ===================================  ==============================
``.exr``    OpenEXR (official bindings)          R, G, B (alpha ignored) or Y;
                                                 half or float
``.hdr``    OpenCV (``cv2.imread``)              Radiance RGBE
``.npy``    NumPy                                2-D, or RGB / RGBA last axis
``.tif``    tifffile                             floating point, 2-D or RGB(A)
==========  ===================================  ==============================

RGB is reduced to luminance ``Y = 0.2126 R + 0.7152 G + 0.0722 B``
(:func:`asynhdr.scene.luminance`). Real EXRs hold small negative values from their
reconstruction filters: they are clipped to 0 and counted (``clipped_negative`` in
the info dict, and a log warning); NaN or infinite values are an error.

Writing (:func:`write_image`) stores a 2-D float32 image by extension: ``.exr``
(one FLOAT channel ``"Y"``, ZIP compression, lossless), ``.hdr`` (RGBE, three equal
channels, about 0.8 % relative precision), ``.npy``, ``.tif``/``.tiff`` (float32),
and ``.png`` (8-bit, tone-mapped by :func:`asynhdr.tonemap.tonemap`). Writes are
atomic. Metadata (a JSON-serialisable dict) goes into the EXR header as the string
attribute ``"asynhdr_metadata"`` and into the TIFF ImageDescription, both as JSON;
:func:`read_metadata` reads it back. ``.hdr``, ``.npy`` and ``.png`` hold none.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import OpenEXR
import tifffile

from asynhdr._atomic import atomic_path
from asynhdr.scene import luminance
from asynhdr.tonemap import tonemap as _tonemap

__all__ = [
    "METADATA_ATTRIBUTE",
    "READ_FORMATS",
    "WRITE_FORMATS",
    "read_image",
    "read_metadata",
    "read_radiance",
    "write_image",
]

logger = logging.getLogger(__name__)

METADATA_ATTRIBUTE = "asynhdr_metadata"
"""Name of the EXR header attribute that holds the metadata, as a JSON string."""

READ_FORMATS: dict[str, str] = {
    ".exr": "exr",
    ".hdr": "hdr",
    ".npy": "npy",
    ".tif": "tiff",
    ".tiff": "tiff",
}
"""Extensions :func:`read_radiance` accepts → format name."""

WRITE_FORMATS: dict[str, str] = {**READ_FORMATS, ".png": "png"}
"""Extensions :func:`write_image` accepts → format name."""

_EXPECTED = {
    "exr": "an OpenEXR image",
    "hdr": "a Radiance RGBE (.hdr) image",
    "npy": "a NumPy .npy array",
    "tiff": "a floating-point TIFF image",
}

PathLike = str | os.PathLike[str]


# --------------------------------------------------------------------------- reading


def _format_of(p: Path, table: Mapping[str, str], what: str) -> str:
    fmt = table.get(p.suffix.lower())
    if fmt is None:
        raise ValueError(
            f"{p}: unsupported extension {p.suffix!r} for {what}; "
            f"supported: {', '.join(sorted(table))}"
        )
    return fmt


def _require_file(p: Path) -> None:
    if not p.is_file():
        reason = "is not a file" if p.exists() else "no such file"
        raise FileNotFoundError(f"{p}: {reason}")


def _not_an_image(p: Path, fmt: str, detail: str) -> ValueError:
    return ValueError(f"{p}: not {_EXPECTED[fmt]} ({detail})")


def _read_exr(p: Path) -> tuple[np.ndarray, list[str]]:
    """Stored channels: ``(h, w)`` for one channel ``Y``, ``(h, w, 3)`` for RGB."""
    if not OpenEXR.isOpenExrFile(str(p)):
        raise _not_an_image(p, "exr", "no OpenEXR magic number 76 2f 31 01 at the start")
    try:
        with OpenEXR.File(str(p), separate_channels=True) as f:
            chans = {name: np.asarray(ch.pixels) for name, ch in f.channels().items()}
    except RuntimeError as e:
        raise _not_an_image(p, "exr", f"OpenEXR cannot decode it: {e}") from e
    names = sorted(chans)
    if {"R", "G", "B"} <= set(chans):
        planes = [chans[c] for c in "RGB"]
        if len({a.shape for a in planes}) != 1:
            raise ValueError(
                f"{p}: channels R, G, B have different shapes "
                f"{[a.shape for a in planes]} (subsampled); expected full-resolution RGB"
            )
        data = np.stack(planes, axis=-1)
        used = ["R", "G", "B"]
    elif "RGB" in chans or "RGBA" in chans:
        key = "RGB" if "RGB" in chans else "RGBA"
        data = chans[key][..., :3]
        used = [key]
    elif "Y" in chans:
        data = chans["Y"]
        used = ["Y"]
    elif len(chans) == 1:
        used = names
        data = chans[names[0]]
    else:
        raise ValueError(
            f"{p}: expected EXR channels R, G, B (alpha ignored) or a single Y channel; "
            f"found {names}"
        )
    if not np.issubdtype(data.dtype, np.floating):
        raise ValueError(
            f"{p}: EXR channels {used} hold {data.dtype} values; expected HALF or FLOAT radiance"
        )
    return data.astype(np.float32, copy=False), used


def _read_hdr(p: Path) -> tuple[np.ndarray, list[str]]:
    bgr = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if bgr is None:
        raise _not_an_image(p, "hdr", "OpenCV cannot decode it")
    if bgr.dtype != np.float32 or bgr.ndim != 3 or bgr.shape[2] != 3:
        raise _not_an_image(
            p, "hdr", f"OpenCV decoded {bgr.dtype} of shape {bgr.shape}, not float32 RGB"
        )
    return bgr[..., ::-1], ["R", "G", "B"]


def _read_npy(p: Path) -> tuple[np.ndarray, list[str]]:
    try:
        a = np.load(p, allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:
        raise _not_an_image(p, "npy", str(e)) from e
    if not isinstance(a, np.ndarray):
        raise _not_an_image(p, "npy", f"np.load returned {type(a).__name__}")
    return a, ["array"]


def _read_tiff(p: Path) -> tuple[np.ndarray, list[str]]:
    try:
        a = tifffile.imread(p)
    except (ValueError, OSError) as e:  # tifffile.TiffFileError is a ValueError
        raise _not_an_image(p, "tiff", str(e)) from e
    if a.ndim == 3 and a.shape[-1] not in (3, 4) and a.shape[0] in (3, 4):
        a = np.moveaxis(a, 0, -1)  # planar (separate) configuration
    return a, ["samples"]


_READERS: dict[str, Callable[[Path], tuple[np.ndarray, list[str]]]] = {
    "exr": _read_exr,
    "hdr": _read_hdr,
    "npy": _read_npy,
    "tiff": _read_tiff,
}


def _to_luminance(p: Path, a: np.ndarray) -> np.ndarray:
    if not np.issubdtype(a.dtype, np.floating):
        raise ValueError(
            f"{p}: holds {a.dtype} values; expected floating-point linear radiance "
            "(convert a linear integer map with .astype(np.float32) and save it again)"
        )
    if a.ndim == 2:
        return a.astype(np.float32, copy=False)
    if a.ndim == 3 and a.shape[-1] in (3, 4):
        return luminance(a[..., :3])
    raise ValueError(
        f"{p}: array of shape {a.shape}; expected (height, width) luminance or "
        "(height, width, 3|4) RGB(A)"
    )


def read_radiance(path: PathLike) -> tuple[np.ndarray, dict[str, Any]]:
    """Read a real HDR image as a linear float32 luminance map ``(height, width)``.

    RGB becomes ``Y = 0.2126 R + 0.7152 G + 0.0722 B``; alpha is ignored. Negative
    luminance (filter undershoot) is clipped to 0 and counted.

    Returns
    -------
    (luminance, info)
        ``info`` has ``source`` (the path), ``format`` (``"exr"``, ``"hdr"``,
        ``"npy"``, ``"tiff"``), ``channels`` (those used), ``width``, ``height``,
        ``clipped_negative`` (pixels with ``Y < 0``, set to 0) and ``non_positive``
        (pixels with ``Y <= 0`` before clipping), ``colour_reduced`` (an RGB image was
        reduced to luminance; also a log warning).

    Raises
    ------
    FileNotFoundError
        The file does not exist.
    ValueError
        Unsupported extension (the message lists the supported ones), a file that
        is not an image of the format its extension names, an unusable layout, or
        NaN / infinite values (with their count).
    """
    p = Path(path)
    fmt = _format_of(p, READ_FORMATS, "read_radiance")
    _require_file(p)
    data, used = _READERS[fmt](p)
    y = _to_luminance(p, data)
    colour_reduced = data.ndim == 3
    if colour_reduced:
        logger.warning("%s: colour (RGB) image reduced to luminance Y = 0.2126 R + 0.7152 G + "
                       "0.0722 B; a colour sensor (Bayer CFA) keeps the colour", p)
    n_bad = int(np.count_nonzero(~np.isfinite(y)))
    if n_bad:
        raise ValueError(
            f"{p}: {n_bad} pixels have NaN or infinite luminance; radiance must be finite"
        )
    neg = y < 0
    n_neg = int(np.count_nonzero(neg))
    n_nonpos = n_neg + int(np.count_nonzero(y == 0))
    if n_neg:
        y = np.where(neg, np.float32(0.0), y)
        logger.info(  # the caller reports it from info["clipped_negative"], once
            "%s: clipped %d negative luminance values to 0 (min %.3g)", p, n_neg,
            float(np.min(data[..., :3] if data.ndim == 3 else data)),
        )
    y = np.ascontiguousarray(y, dtype=np.float32)
    info: dict[str, Any] = {
        "source": str(p),
        "format": fmt,
        "channels": used,
        "width": int(y.shape[1]),
        "height": int(y.shape[0]),
        "clipped_negative": n_neg,
        "non_positive": n_nonpos,
        "colour_reduced": colour_reduced,
    }
    return y, info


def read_image(path: PathLike) -> np.ndarray:
    """Read back an image written by :func:`write_image` (``.exr``, ``.npy``, ``.tif``).

    Returns the stored values as float32, unchanged (bit-exact for float32 data):
    ``(height, width)`` for one channel, ``(height, width, 3)`` for EXR RGB (alpha
    dropped). For ``.hdr`` files use :func:`read_radiance` (RGBE is not exact).
    """
    p = Path(path)
    table = {k: v for k, v in READ_FORMATS.items() if v != "hdr"}
    fmt = _format_of(p, table, "read_image")
    _require_file(p)
    data, _ = _READERS[fmt](p)
    if not np.issubdtype(data.dtype, np.floating):
        raise ValueError(f"{p}: holds {data.dtype} values; expected floating point")
    return np.ascontiguousarray(data, dtype=np.float32)


def read_metadata(path: PathLike) -> dict[str, Any]:
    """The metadata dict :func:`write_image` stored (EXR, TIFF); ``{}`` if there is none."""
    p = Path(path)
    fmt = _format_of(p, WRITE_FORMATS, "read_metadata")
    _require_file(p)
    text: str | None = None
    if fmt == "exr":
        if not OpenEXR.isOpenExrFile(str(p)):
            raise _not_an_image(p, "exr", "no OpenEXR magic number 76 2f 31 01 at the start")
        with OpenEXR.File(str(p), header_only=True) as f:
            value = f.header().get(METADATA_ATTRIBUTE)
        text = value if isinstance(value, str) else None
    elif fmt == "tiff":
        try:
            with tifffile.TiffFile(p) as tif:
                text = tif.pages.first.description or None
        except (ValueError, OSError) as e:
            raise _not_an_image(p, "tiff", str(e)) from e
    if not text:
        return {}
    try:
        meta = json.loads(text)
    except json.JSONDecodeError:
        return {}
    return meta if isinstance(meta, dict) else {}


# --------------------------------------------------------------------------- writing


def _json_default(o: object) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, os.PathLike):
        return os.fspath(o)
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


def _write_exr(tmp: Path, a: np.ndarray, meta: str | None) -> None:
    header: dict[str, Any] = {
        "compression": OpenEXR.ZIP_COMPRESSION,
        "type": OpenEXR.scanlineimage,
    }
    if meta is not None:
        header[METADATA_ATTRIBUTE] = meta
    with OpenEXR.File(header, {"Y": a}) as f:
        f.write(str(tmp))


def _write_hdr(tmp: Path, a: np.ndarray, meta: str | None) -> None:
    if not cv2.imwrite(str(tmp), np.ascontiguousarray(np.dstack([a, a, a]))):
        raise OSError(f"{tmp}: OpenCV failed to write the Radiance .hdr image")


def _write_npy(tmp: Path, a: np.ndarray, meta: str | None) -> None:
    with open(tmp, "wb") as f:
        np.save(f, a, allow_pickle=False)


def _write_tiff(tmp: Path, a: np.ndarray, meta: str | None) -> None:
    tifffile.imwrite(tmp, a, description=meta, metadata=None)


def _write_png(tmp: Path, a: np.ndarray, meta: str | None) -> None:
    if not cv2.imwrite(str(tmp), a):
        raise OSError(f"{tmp}: OpenCV failed to write the PNG image")


_WRITERS: dict[str, Callable[[Path, np.ndarray, str | None], None]] = {
    "exr": _write_exr,
    "hdr": _write_hdr,
    "npy": _write_npy,
    "tiff": _write_tiff,
    "png": _write_png,
}


def write_image(
    path: PathLike,
    image: npt.ArrayLike,
    *,
    metadata: Mapping[str, Any] | None = None,
    tonemap: str = "log",
    tonemap_options: Mapping[str, Any] | None = None,
    allow_nan: bool = False,
) -> Path:
    """Write a 2-D linear image ``(height, width)`` to ``path``, format by extension.

    ``.exr``: float32 channel ``"Y"``, ZIP (lossless), metadata as the JSON string
    attribute ``"asynhdr_metadata"``; ``.hdr``: RGBE with R = G = B (non-negative
    values only); ``.npy``: float32; ``.tif``/``.tiff``: float32, metadata as JSON
    in the ImageDescription; ``.png``: 8-bit grey from
    ``asynhdr.tonemap.tonemap(image, method=tonemap, **tonemap_options)``.
    The image is stored as float32. The write is atomic: on any error nothing
    appears under ``path`` and no temporary file is left.

    With ``allow_nan``, NaN marks pixels without a value: kept in ``.exr``, ``.npy`` and
    ``.tif``, drawn black in ``.png``, refused by ``.hdr``.

    Returns
    -------
    pathlib.Path
        ``path``.

    Raises
    ------
    ValueError
        Unsupported extension, not 2-D, not real, NaN (unless ``allow_nan``) / infinite
        values (with their count), negative values for ``.hdr``, metadata that is not
        JSON-serialisable. Nothing is written.
    """
    p = Path(path)
    fmt = _format_of(p, WRITE_FORMATS, "write_image")
    a = np.asarray(image)
    if a.ndim != 2:
        raise ValueError(f"{p}: write_image expects a 2-D (height, width) image, got {a.shape}")
    if a.size == 0:
        raise ValueError(f"{p}: write_image got an empty image of shape {a.shape}")
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise ValueError(f"{p}: write_image expects real numbers, got dtype {a.dtype}")
    with np.errstate(over="ignore", invalid="ignore"):
        a = np.ascontiguousarray(a, dtype=np.float32)
    nan = np.isnan(a) if allow_nan and fmt != "hdr" else None
    n_bad = int(np.count_nonzero(~np.isfinite(a))) - (int(nan.sum()) if nan is not None else 0)
    if n_bad:
        raise ValueError(
            f"{p}: image has {n_bad} NaN or infinite values (after conversion to float32); "
            "nothing written"
        )
    if fmt == "hdr" and bool(np.any(a < 0)):
        raise ValueError(
            f"{p}: Radiance RGBE cannot store the image's {int(np.count_nonzero(a < 0))} "
            "negative values; clip them or write .exr / .npy / .tiff"
        )
    meta_json: str | None = None
    if metadata is not None:
        try:
            meta_json = json.dumps(dict(metadata), default=_json_default, allow_nan=False)
        except (TypeError, ValueError) as e:
            raise ValueError(f"{p}: metadata is not JSON-serialisable: {e}") from e
        if fmt in ("hdr", "npy", "png"):
            logger.warning("%s: .%s files hold no metadata; metadata not stored", p, fmt)
    payload = a
    if fmt == "png":
        if nan is not None and nan.any():
            if nan.all():
                payload = np.zeros(a.shape, np.uint8)
            else:
                fill = np.where(nan, float(np.nanmin(a)), a)
                payload = _tonemap(fill, method=tonemap, **dict(tonemap_options or {}))
                payload = np.where(nan, 0, payload).astype(payload.dtype)
        else:
            payload = _tonemap(a, method=tonemap, **dict(tonemap_options or {}))
    with atomic_path(p) as tmp:
        _WRITERS[fmt](tmp, payload, meta_json)
    return p
