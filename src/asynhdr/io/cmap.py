"""Save and load c-maps (``.npz``: one float32 array per weighting, metadata as JSON)."""

from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path

import numpy as np

from asynhdr._atomic import atomic_path
from asynhdr.calibrate import CMap

__all__ = ["load_cmap", "save_cmap"]

_PREFIX = "cmap__"


def save_cmap(path: str | os.PathLike[str], cmap: CMap, *, overwrite: bool = True) -> Path:
    """Write ``cmap`` to ``path`` (``.npz``), atomically (``overwrite`` False refuses an
    existing file)."""
    target = Path(path)
    arrays = {_PREFIX + k: np.asarray(v, dtype=np.float32) for k, v in cmap.maps.items()}
    arrays["metadata"] = np.asarray(json.dumps(cmap.metadata))
    with atomic_path(target, overwrite=overwrite) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, **arrays)  # type: ignore[arg-type]
    return target


def load_cmap(path: str | os.PathLike[str]) -> CMap:
    """Read a c-map written by ``save_cmap``; ``ValueError`` naming the file otherwise."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: c-map file not found")
    try:
        with np.load(p, allow_pickle=False) as z:
            maps = {k[len(_PREFIX):]: z[k] for k in z.files if k.startswith(_PREFIX)}
            meta = json.loads(str(z["metadata"])) if "metadata" in z.files else {}
    except (OSError, ValueError, zipfile.BadZipFile, json.JSONDecodeError) as exc:
        raise ValueError(f"{p}: not a c-map .npz file ({exc})") from None
    if not maps:
        raise ValueError(f"{p}: no c-map arrays (expected keys starting with {_PREFIX!r})")
    shapes = {m.shape for m in maps.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise ValueError(f"{p}: c-map arrays must be 2-D and of one shape, got {shapes}")
    return CMap(maps=maps, metadata=meta)
