"""The ``asynhdr`` command line: subcommands wire the library together.

Each subcommand lives in its own module, which registers itself on ``app``
(:mod:`asynhdr.cli._app`); :func:`_register` imports them all.
"""

from __future__ import annotations

from asynhdr.cli._app import app


def _register() -> None:
    # Each import adds its commands to ``app``.
    from asynhdr.cli import (  # noqa: F401
        bench,
        calib,
        convert,
        core,
        design,
        generator,
        info,
        reconstruct,
        video,
        waveform,
    )


def main() -> None:
    """Entry point of the ``asynhdr`` script. The process keeps the memory it frees for
    its next allocations (:func:`asynhdr.memory.retain_freed_memory`; environment
    ``ASYNHDR_RETAIN_MEMORY=0`` to hand it back)."""
    from asynhdr.memory import retain_freed_memory

    retain_freed_memory()
    _register()
    app()


__all__ = ["app", "main"]
