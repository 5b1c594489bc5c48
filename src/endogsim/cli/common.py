"""Helpers shared by CLI commands: user-facing errors, progress bars, tables, JSON output."""

from __future__ import annotations

import functools
import os
import warnings
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any, TypeVar

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Table

from endogsim.errors import EndoGSimError

# Piped or logged output (no terminal) gets a wide console so tables are not cut to 80 columns.
_WIDTH = None if os.isatty(1) or os.environ.get("COLUMNS") else 160
console = Console(stderr=False, width=_WIDTH)
err_console = Console(stderr=True)
F = TypeVar("F", bound=Callable[..., Any])

#: ``--optimizer`` of ``identify``, ``run`` and ``validate`` (:attr:`endogsim.identify.IdentifyConfig.optimizer`).
OPTIMIZER_HELP = ("rprop (steps grow while the gradient keeps its direction) | adam | lm (Levenberg-Marquardt, forward "
                  "simulations side by side, no adjoint).")
#: ``--refine`` of ``identify``, ``run``, ``validate`` and ``simulate``
#: (:attr:`endogsim.identify.IdentifyConfig.refine`).
REFINE_WHAT = ("Simulate at the scene's identification discretisation refined by this factor: grid x F, particle "
               "spacing / F, substeps x F; nearer converged, up to F^4 the time and F^3 the memory")
REFINE_HELP = REFINE_WHAT + " (1: the default)."
#: ``--refined-correction`` of ``identify``, ``run`` and ``validate``
#: (:attr:`endogsim.identify.IdentifyConfig.refined_correction`).
REFINED_CORRECTION_HELP = ("Correct what the video determines to the discretisation refined this many times (forward "
                           "simulations; 0: none). Default 1.5.")
#: ``--time-budget`` of ``identify``, ``run`` and ``validate`` (:attr:`endogsim.identify.IdentifyConfig.time_budget`).
TIME_BUDGET_HELP = ("Safety stop: no new iteration starts after this many seconds of optimisation (the best so far is "
                    "kept, and the run says it was stopped; the schedule follows the iterations only); 0: no stop.")


def time_budget_option(seconds: float | None) -> dict:
    """The ``time_budget`` an identification config gets from ``--time-budget`` (0: none; not given: the
    config's default)."""
    return {} if seconds is None else {"time_budget": seconds or None}


def print_budget_stops(stops: dict[str, int | None]) -> None:
    """One yellow line for each stage its time budget stopped (stage -> the iterations it ran): a safety stop,
    so what that stage kept depends on this machine's speed, which the closing lines must not hide."""
    for stage, iterations in stops.items():
        console.print(f"[yellow]{stage} was stopped by its time budget (a safety stop) after {iterations} iterations: "
                      "its result depends on this machine's speed[/]")


#: ``--device`` of ``run`` and ``validate``: where the calibration, the prediction and the simulation run.
DEVICE_HELP = ("cpu | cuda: the simulator and renderer of the identification (calibration), prediction and simulation "
               "(the reconstruction picks its own device). The same computation; on CUDA sums run in another order.")


def user_errors(func: F) -> F:
    """Turn an :class:`EndoGSimError` into a one-line red message and exit code 2 (no traceback).

    An ``OSError`` that names its file (a read-only folder, a full disk, a path that is a file) is
    reported the same way: the file and the system's reason.
    """

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return func(*args, **kwargs)
        except EndoGSimError as exc:
            _error(str(exc))
        except OSError as exc:
            if exc.filename is None:
                raise
            _error(f"{exc.filename}: {exc.strerror or type(exc).__name__}")

    return wrapper  # type: ignore[return-value]


def output_folder(value: Path | None) -> Path | None:
    """``--out`` callback: the working folder itself (``.``, or an empty ``--out ""``, which reads the same,
    as from an unset shell variable) is refused: a run folder's files would land among the user's own, and a
    replaced folder would take them with it."""
    if value is not None and value.resolve() == Path.cwd().resolve():  # Path("") is Path(".")
        raise typer.BadParameter(f"name a folder to write (got the working folder {str(value)!r}; an empty "
                                 "--out \"\" reads as '.')")
    return value


def _error(message: str) -> None:
    # soft_wrap: one line, however narrow the terminal (a log or a test reads the first line)
    err_console.print(f"[bold red]error:[/] {escape(message)}", highlight=False, markup=True, soft_wrap=True)
    raise typer.Exit(code=2) from None


def show_warnings_as_lines() -> None:
    """Print every warning as one yellow line on stderr ("warning: ..."), without Python's file and line."""

    def show(message, category, filename, lineno, file=None, line=None) -> None:  # noqa: ANN001 - warnings API
        err_console.print(f"[yellow]warning:[/] {escape(str(message))}", highlight=False, soft_wrap=True)

    warnings.showwarning = show


def unwrap_help(app: typer.Typer) -> None:
    """Give each of ``app``'s commands its docstring as help with the source's line breaks joined (paragraphs
    kept): Typer's command list prints a docstring's line breaks as they are, which broke every description in
    ``endogsim --help`` at the docstring's 120-column source lines."""
    import inspect

    for command in app.registered_commands:
        doc = command.help or inspect.getdoc(command.callback) or ""
        command.help = "\n\n".join(" ".join(p.split()) for p in doc.split("\n\n")) or None


def progress() -> Progress:
    """A rich progress bar with count, elapsed and remaining time (quiet when not a terminal)."""
    return Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
        TimeElapsedColumn(), TimeRemainingColumn(), console=err_console, transient=False,
        # the refresh thread takes the GIL from the training loop and the Warp launch threads: 2 Hz is enough
        refresh_per_second=2,
    )


def track(items: Iterable, description: str, total: int | None = None) -> Iterable:
    """Iterate with a progress bar."""
    with progress() as bar:
        task = bar.add_task(description, total=total if total is not None else len(items))  # type: ignore[arg-type]
        for item in items:
            yield item
            bar.advance(task)


def print_table(title: str, columns: Sequence[str], rows: Iterable[Sequence[Any]]) -> None:
    table = Table(title=title)
    for c in columns:
        table.add_column(c)
    for row in rows:
        table.add_row(*[_fmt(v) for v in row])
    console.print(table)


def fmt_optional(v: Any, spec: str) -> str:
    """``v`` formatted with ``spec``, "-" when it is None."""
    return "-" if v is None else format(v, spec)


def with_interval(v: Any, interval: Sequence[float] | None, spec: str) -> str:
    """``v`` and its 90% interval, e.g. "2473 [1715, 3085]" ("-" when ``v`` is None)."""
    if interval is None:
        return fmt_optional(v, spec)
    return f"{fmt_optional(v, spec)} [{format(interval[0], spec)}, {format(interval[1], spec)}]"


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)
