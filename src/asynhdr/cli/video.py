"""``asynhdr video``: a recording as HDR video, one frame per modulation cycle."""

from __future__ import annotations

import math
from collections.abc import Iterator
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
import typer

from asynhdr.cli._app import app
from asynhdr.cli.core import check_outputs, console, fail, progress_bar
from asynhdr.reconstruct import DEFAULT_K, DEFAULT_METHOD, METHODS

__all__ = ["video"]


def _fps(starts_us: np.ndarray, metadata: dict[str, Any]) -> Fraction:
    """Frames per second: one frame per cycle, at the cycles' median period."""
    if starts_us.size > 1:
        period = round(float(np.median(np.diff(starts_us))))
    else:
        period = int((metadata.get("rig") or {}).get("period_us") or 50_000)
    return Fraction(1_000_000, max(period, 1))


@app.command()
def video(
    recording: Path = typer.Argument(..., help="Event recording (any supported format)."),
    out: Path = typer.Option(..., "--out", "-o", help="Video to write (.mp4)."),
    method: str = typer.Option(DEFAULT_METHOD, help=" | ".join(METHODS) + "."),
    k: float = typer.Option(DEFAULT_K, help="k of the exponential weighting."),
    cmap: Path | None = typer.Option(None, help="c-map from 'asynhdr calibrate'."),
    exr_dir: Path | None = typer.Option(None, "--exr-dir", help="Also write each frame as "
                                        "linear EXR here, named by cycle and start time."),
    tau_frames: float = typer.Option(10.0, help="Time constant (frames) of the tone curve's "
                                     "black and white points: larger is steadier."),
    period_us: float | None = typer.Option(None, help="Modulation period in µs, when known."),
    crf: int = typer.Option(12, help="H.264 quality: 0 lossless, 23 x264's default."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace existing outputs."),
) -> None:
    """Reconstruct every cycle and write them as an H.264 MP4 at the modulation's rate,
    tone-mapped with a log curve whose black and white points move slowly (no flicker);
    optionally an EXR sequence with each frame's start time in its name and metadata."""
    from asynhdr.io import open_source
    from asynhdr.io.cmap import load_cmap
    from asynhdr.io.images import write_image
    from asynhdr.io.video import write_video
    from asynhdr.reconstruct import reconstruct_cycles
    from asynhdr.segment import NoCyclesError
    from asynhdr.tonemap import StableLogToneCurve

    if method not in METHODS:
        fail(f"--method: unknown method {method!r}; choose from {list(METHODS)}")
    if out.suffix.lower() != ".mp4":
        fail(f"{out}: the video is written as .mp4")
    if not (tau_frames >= 0 and math.isfinite(tau_frames)):
        fail(f"--tau-frames must be a finite number >= 0, got {tau_frames}")
    check_outputs([out], overwrite=overwrite)
    try:
        src = open_source(recording)
        cm = load_cmap(cmap) if cmap is not None else None
        with progress_bar() as update:
            plan = reconstruct_cycles(src, method=method, k=k, cmap=cm, period_us=period_us,
                                      progress=update)
            starts = plan.windows.start_us
            fps = _fps(starts, plan.metadata)
            curve = StableLogToneCurve(tau_frames=tau_frames)
            unit = plan.metadata.get("radiance_unit", "relative")

            def frames() -> Iterator[np.ndarray]:
                for i, start_us, img in plan:
                    if exr_dir is not None:
                        meta = {"source": str(recording), "method": method, "cycle": i,
                                "start_us": int(start_us), "unit": unit,
                                "radiometric": METHODS[method].radiometric}
                        write_image(exr_dir / f"{recording.stem}_{i:04d}_t{int(start_us)}us.exr",
                                    img, metadata=meta)
                    yield curve(img)

            n = write_video(out, frames(), fps=fps, crf=crf, overwrite=overwrite,
                            metadata={"comment": f"asynhdr {method} of {recording.name}, "
                                      f"one frame per modulation cycle"})
    except NoCyclesError as exc:
        fail(f"{recording}: no cycles found ({exc.reason}); pass --period-us; nothing written")
    except (ValueError, OSError) as exc:
        fail(str(exc))
    console.print(f"{n} frames at {float(fps):g} fps ({method}, tone curve tau "
                  f"{tau_frames:g} frames) -> {out}"
                  + (f"; EXR frames in {exr_dir}/" if exr_dir is not None else ""))
