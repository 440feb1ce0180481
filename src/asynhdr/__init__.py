"""asynhdr: event-based asynchronous HDR imaging by temporal incident light modulation.

Simulate the rig (scene radiance -> two LCD-modulated light paths -> DVS pixels), read
and write real event recordings, split them into modulation cycles, calibrate, and
reconstruct HDR images (Wu et al., Optics Express 32(11), 2024).
"""

__version__ = "0.1.0"

__all__ = ["__version__"]
