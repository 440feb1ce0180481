"""Video files: a sequence of 8-bit display frames as H.264 in MP4, through PyAV.

PyAV wraps FFmpeg's own libraries (its wheels ship them). Frames are grey
``(height, width)`` uint8; they are encoded as 4:2:0 YUV with the grey in the luma
plane (chroma neutral), so a grey frame decodes back to within the codec's error. H.264
needs even sizes: an odd width or height is padded by repeating the last column or row
(the metadata says so). The file is written atomically.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

from asynhdr._atomic import atomic_path

__all__ = ["VIDEO_CRF", "read_video", "video_info", "write_video"]

logger = logging.getLogger(__name__)

VIDEO_CRF = 12
"""x264 constant rate factor: 0 is lossless, 23 x264's default; 12 keeps a tone-mapped
frame within a few grey levels of the original."""


def _even(frame: np.ndarray) -> np.ndarray:
    h, w = frame.shape
    if h % 2 or w % 2:
        frame = np.pad(frame, ((0, h % 2), (0, w % 2)), mode="edge")
    return frame


def write_video(
    path: str | os.PathLike[str],
    frames: Iterable[np.ndarray],
    *,
    fps: Fraction | float,
    crf: int = VIDEO_CRF,
    metadata: dict[str, str] | None = None,
    overwrite: bool = True,
) -> int:
    """Encode grey uint8 frames ``(height, width)`` as H.264 (libx264) in an MP4 at
    ``fps`` frames per second; returns the number of frames written.

    ``metadata`` goes into the container's tags (e.g. ``comment``). All frames must have
    the first one's shape. Raises ``ValueError`` for bad frames or no frames; the file
    appears only when every frame was encoded.
    """
    import av

    rate = Fraction(fps).limit_denominator(1_000_000)
    if not rate > 0:
        raise ValueError(f"write_video: fps must be positive, got {fps}")
    target = Path(path)
    n = 0
    with atomic_path(target, overwrite=overwrite) as tmp:
        container = av.open(str(tmp), mode="w", format="mp4")
        try:
            stream: Any = None
            shape: tuple[int, int] | None = None
            for frame in frames:
                f = np.asarray(frame)
                if f.ndim != 2 or f.dtype != np.uint8:
                    raise ValueError(f"{target}: frame {n}: expected a 2-D uint8 image, got "
                                     f"{f.dtype} of shape {f.shape}")
                if shape is None:
                    shape = f.shape
                    even = _even(f)
                    stream = container.add_stream("libx264", rate=rate)
                    stream.width = even.shape[1]
                    stream.height = even.shape[0]
                    stream.pix_fmt = "yuv420p"
                    stream.options = {"crf": str(int(crf))}
                    for key, value in (metadata or {}).items():
                        container.metadata[key] = value
                elif f.shape != shape:
                    raise ValueError(f"{target}: frame {n} has shape {f.shape}, the first "
                                     f"{shape}")
                grey = _even(f)
                vf = av.VideoFrame.from_ndarray(grey, format="gray")
                for packet in stream.encode(vf):
                    container.mux(packet)
                n += 1
            if stream is None:
                raise ValueError(f"{target}: no frames to write")
            for packet in stream.encode():
                container.mux(packet)
        finally:
            container.close()
    logger.info("%s: %d frames at %s fps", target, n, rate)
    return n


def video_info(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Frame count, rate, size, duration and codec of a video file (as its container
    says; the count by decoding when the container does not)."""
    import av

    with av.open(str(path)) as c:
        s = c.streams.video[0]
        frames = int(s.frames) or sum(1 for _ in c.decode(s))
        return {"frames": frames, "fps": Fraction(s.average_rate) if s.average_rate else None,
                "width": int(s.codec_context.width), "height": int(s.codec_context.height),
                "codec": s.codec_context.name,
                "duration_s": (float(s.duration * s.time_base)
                               if s.duration and s.time_base else None),
                "metadata": dict(c.metadata)}


def read_video(path: str | os.PathLike[str]) -> np.ndarray:
    """All frames of a video as grey uint8 ``(n, height, width)`` (the luma plane)."""
    import av

    with av.open(str(path)) as c:
        return np.stack([f.to_ndarray(format="gray") for f in c.decode(video=0)])
