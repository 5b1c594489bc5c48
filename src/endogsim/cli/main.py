"""The ``endogsim`` command line. Each capability registers its commands from its own module."""

from __future__ import annotations

import typer

from endogsim.cli import common

app = typer.Typer(
    name="endogsim",
    help="Physics-aware 4D endoscopic scenes: Gaussian splats, material field, differentiable MPM.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
)
bench_app = typer.Typer(help="Benchmarks that print a table (and write JSON with --json).", no_args_is_help=True)
app.add_typer(bench_app, name="bench")
materials_app = typer.Typer(help="Material field: initialise, show.", no_args_is_help=True)
app.add_typer(materials_app, name="materials")


def _print_version(value: bool) -> None:
    if value:
        from endogsim import __version__

        typer.echo(__version__)
        raise typer.Exit()


@app.callback()
def _main(version: bool = typer.Option(False, "--version", callback=_print_version, is_eager=True,
                                       help="Print the version and exit.")) -> None:
    # Eager: the version is printed before the group asks for a command (without it, `endogsim --version`
    # ended in "Missing command.").
    pass


def _register() -> None:
    # Each module owns its commands; importing it must stay cheap (heavy imports inside commands).
    from endogsim.cli import (
        bench,
        demo,
        identify,
        info,
        materials,
        reconstruct,
        simulate,
        synth,
    )

    for module in (info, demo, synth, reconstruct, identify, simulate):  # demo also adds `run`
        module.register(app)
    materials.register(materials_app)
    bench.register(bench_app)
    for commands in (app, bench_app, materials_app):
        common.unwrap_help(commands)


_register()
common.show_warnings_as_lines()
