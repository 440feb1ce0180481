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
    """Entry point of the ``asynhdr`` script."""
    _register()
    app()


__all__ = ["app", "main"]
