"""The ``asynhdr`` Typer application and its root options (``--verbose``, ``--version``).

Command modules import ``app`` from here and register themselves with ``@app.command``;
:mod:`asynhdr.cli` imports them, so no module imports its importer."""

from __future__ import annotations

import logging

import typer

from asynhdr import __version__

__all__ = ["app"]

app = typer.Typer(
    name="asynhdr",
    help="Event-based asynchronous HDR imaging by temporal light modulation.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _show_version(value: bool) -> None:
    if value:
        typer.echo(f"asynhdr {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Log progress."),
    version: bool = typer.Option(False, "--version", callback=_show_version, is_eager=True,
                                 help="Print the version and exit."),
) -> None:
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
