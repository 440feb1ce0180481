"""The ``asynhdr`` command line: subcommands wire the library together.

Each subcommand lives in its own module and registers itself on ``app``.
"""

from __future__ import annotations

import logging

import typer

app = typer.Typer(
    name="asynhdr",
    help="Event-based asynchronous HDR imaging by temporal light modulation.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


@app.callback()
def _root(verbose: bool = typer.Option(False, "--verbose", "-v", help="Log progress.")) -> None:
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )


def _register() -> None:
    # Each import adds its commands to ``app``.
    from asynhdr.cli import bench, core, design, generator, info, waveform  # noqa: F401


def main() -> None:
    """Entry point of the ``asynhdr`` script."""
    _register()
    app()


__all__ = ["app", "main"]
