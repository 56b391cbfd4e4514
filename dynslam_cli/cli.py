"""The `dynslam` command line: a thin layer over the library.

Each command parses its arguments and calls one library function that returns a result object.
Command modules live in ``dynslam_cli/commands/`` and each exposes ``register(app)``; heavy
imports (torch, evo, onnxruntime, ...) happen inside the command bodies so `dynslam --help`
stays instant.  Every :class:`~dynslam_cli.errors.DynslamError` becomes one line on stderr and
exit code 2, and so does an OS error (a read-only or full disk, a folder that is a file): the line
names the path and the reason.
"""

from __future__ import annotations

import errno
import importlib
import pkgutil

import typer
from typer.core import TyperGroup

from dynslam_cli.errors import DynslamError


class DynslamGroup(TyperGroup):
    """A command group that turns user errors into one readable line and exit code 2."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except DynslamError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(code=exc.exit_code) from None
        except FileNotFoundError as exc:
            typer.echo(f"error: file not found: {exc.filename or exc}", err=True)
            raise typer.Exit(code=2) from None
        except OSError as exc:
            typer.echo(f"error: {os_error_line(exc)}", err=True)
            raise typer.Exit(code=2) from None


_HINTS = {  # where the system's reason alone does not say what to fix
    errno.ENOTDIR: "a part of the path is a file, not a folder",
    errno.EEXIST: "something already exists there, e.g. a file where a folder is needed",
    errno.EISDIR: "it is a folder",
}


def os_error_line(exc: OSError) -> str:
    """One line for an OS error: the path(s) it concerns and the reason."""
    reason = " ".join(str(exc.strerror or exc).split())
    hint = _HINTS.get(exc.errno) if exc.errno is not None else None
    if hint:
        reason = f"{reason} ({hint})"
    if exc.filename is None:
        return reason if exc.strerror else f"{type(exc).__name__}: {reason}"
    where = str(exc.filename)
    if exc.filename2 is not None:
        where = f"{where} -> {exc.filename2}"
    return f"file system error at {where}: {reason}"


def make_group(help: str) -> typer.Typer:  # noqa: A002
    return typer.Typer(cls=DynslamGroup, help=help, no_args_is_help=True,
                       add_completion=False, pretty_exceptions_enable=False)


app = make_group("Dense neural RGB-D SLAM that learns to forget moving objects.")

COMMAND_ORDER = ("synth", "data", "run", "demo", "evaluate", "experiments", "motion", "config")


def _register_commands() -> None:
    import dynslam_cli.commands as pkg

    names = sorted(m.name for m in pkgutil.iter_modules(pkg.__path__) if not m.name.startswith("_"))
    names.sort(key=lambda n: COMMAND_ORDER.index(n) if n in COMMAND_ORDER else len(COMMAND_ORDER))
    for name in names:
        module = importlib.import_module(f"dynslam_cli.commands.{name}")
        register = getattr(module, "register", None)
        if register is not None:
            register(app)


_register_commands()


def main() -> None:
    app()


if __name__ == "__main__":
    main()
