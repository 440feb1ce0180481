"""Colour wiring for ``simulate --cfa`` and ``reconstruct``: a colour scene from an RGB
file, and the demosaiced RGB output of a colour recording."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["DEMOSAIC_CHOICES", "colour_scene_from_file", "write_colour"]

DEMOSAIC_CHOICES = ("malvar", "bilinear", "none")


def colour_scene_from_file(spec: str, *, width: int, height: int, scale: float | None,
                           cfa: str, target: float) -> Any:
    """The :class:`asynhdr.colour.ColourScene` of an RGB HDR image behind a Bayer CFA;
    without ``scale``, the automatic exposure puts the luminance's log-average at
    ``target``."""
    from asynhdr.colour import colour_scene
    from asynhdr.io.colour_images import read_rgb_radiance
    from asynhdr.scene import exposure_scale, luminance

    rgb, _ = read_rgb_radiance(spec)
    if scale is None:
        scale = exposure_scale(luminance(rgb), target=target)
    return colour_scene(rgb, width=width, height=height, pattern=cfa, scale=scale,
                        name=Path(spec).stem, unit="lux", fit="pad")


def write_colour(stem: Path, image: np.ndarray, metadata: dict[str, Any], formats: list[str],
                 *, method: str, tonemap: str, extra: dict[str, Any]) -> None:
    """Demosaic one reconstructed mosaic and write it as RGB in every format."""
    from asynhdr.colour import reconstruct_colour
    from asynhdr.io.colour_images import write_rgb_image

    cfa = str(metadata["cfa"])
    t = metadata.get("cfa_transmittance") or (1.0, 1.0, 1.0)
    rgb = reconstruct_colour(image, cfa, transmittance=t, method=method)
    info = dict(extra, cfa=cfa, demosaic=method, demosaic_domain="log", colour="linear RGB")
    for f in formats:
        write_rgb_image(stem.parent / f"{stem.name}.{f}", rgb, tonemap=tonemap,
                        metadata=info if f in ("exr", "tif") else None)
