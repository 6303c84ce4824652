"""The ``voxfusion`` command line. Each subcommand lives in ``voxfusion/commands/<name>.py`` and exposes
``register(app)``; this file only assembles them."""

from __future__ import annotations

import importlib

import typer

from voxfusion.core.errors import VoxFusionError

app = typer.Typer(
    name="voxfusion",
    help="Vox-Fusion dense RGB-D SLAM: evaluate, map, run, serve, stream, encode and view.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

_COMMAND_MODULES = (
    "voxfusion.commands.synth",
    "voxfusion.commands.eval",
    "voxfusion.commands.map",
    "voxfusion.commands.run",
    "voxfusion.commands.serve",
    "voxfusion.commands.stream",
    "voxfusion.commands.encode",
    "voxfusion.commands.bridge",
    "voxfusion.commands.view",
)

for _name in _COMMAND_MODULES:
    importlib.import_module(_name).register(app)


def main() -> None:
    """Console-script entry point: runs the app and turns voxfusion errors into one clear line."""
    try:
        app()
    except VoxFusionError as e:
        typer.secho(f"error: {e}", fg=typer.colors.RED, err=True)
        raise SystemExit(2) from e


if __name__ == "__main__":
    main()
