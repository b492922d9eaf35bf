"""The ``isolume`` command line (DESIGN §6): the parser and the entry point.

The options live in `app.options`, the ``info``, ``render`` and ``bake`` commands in
`app.commands`, the other commands in their own modules (`COMMAND_MODULES`). Every user
error (an `IsolumeError`: bad file, bad value, missing GL) ends in a one-line message on
stderr and exit status 2; no tracebacks. Heavy modules are imported inside the commands
so that ``isolume info`` and ``isolume bake`` never load OpenGL. ``--state FILE`` (render,
movie, view) gives a command the defaults of a view saved in the viewer
(`app.state.apply_state`): options given on the command line win.
"""

from __future__ import annotations

import argparse
import difflib
import gc
import os
import re
import sys
import threading
from collections.abc import Callable, Sequence

from isolume.app import blas  # first: before numpy loads its BLAS
from isolume.app.allocator import tune_malloc
from isolume.app.commands import cmd_bake, cmd_info, cmd_render
from isolume.app.options import (
    EXIT_INTERRUPTED,
    EXIT_USER_ERROR,
    add_bake_options,
    add_render_options,
    add_timeline_option,
    add_volume_options,
    description_of,
)
from isolume.app.state import add_state_argument, apply_state
from isolume.volumes import cores, interrupts
from isolume.volumes.errors import IsolumeError, interrupted_by

COMMANDS: dict[str, Callable[[argparse.Namespace], int]] = {
    "info": cmd_info,
    "render": cmd_render,
    "bake": cmd_bake,
}

COMMAND_MODULES = {
    "view": "isolume.app.viewer.window",
    "reference": "isolume.app.reference",
    "chart": "isolume.app.charts.charts",
    "bench": "isolume.app.bench.commands",
    "movie": "isolume.app.movie",
    "export": "isolume.app.export",
}
"""Commands that live in their own modules. Each module provides ``HELP`` (one line),
``add_arguments(parser)`` and ``run(args) -> int``, and is imported only when present."""


def _command_module(name: str):
    import importlib
    import importlib.util

    module = COMMAND_MODULES[name]
    if importlib.util.find_spec(module) is None:
        return None
    return importlib.import_module(module)


BUILT_IN = {
    "info": ("describe a volume and suggest isovalues",
             "Describe a volume (shape, type, spacing, placement, value histogram) and "
             "suggest isovalues that show its structure."),
    "render": ("render an isosurface off-screen to PNG or EXR",
               "Render an isosurface off-screen to PNG (sRGB) or EXR (linear). Without "
               "--lattice the view's global illumination is traced for the texels the "
               "picture reads (28 paths a texel on average, placed where the picture's "
               "noise is, their first directions stratified)."),
    "bake": ("bake an illumination lattice with Embree path tracing",
             "Bake an illumination lattice for every isovalue (or --iso-range) with Embree "
             "path tracing; Ctrl-C keeps the finished texels."),
}
"""(help, description) of the commands `app.commands` runs."""


def add_command_arguments(name: str, p: argparse.ArgumentParser) -> None:
    """The arguments of command `name` (one of `COMMANDS` or `COMMAND_MODULES`)."""
    if name == "info":
        add_volume_options(p, optional=False)
    elif name == "render":
        add_volume_options(p, optional=True)
        p.add_argument("--out", help="FILE.png (sRGB) or FILE.exr (linear) (required; with "
                       "--state, by default beside the state file: NAME-WxH.png)")
        add_render_options(p)
        add_timeline_option(p)
        add_state_argument(p)
    elif name == "bake":
        add_volume_options(p, optional=False)
        add_bake_options(p)
        add_timeline_option(p)
    else:
        _command_module(name).add_arguments(p)


def command_parser(name: str) -> argparse.ArgumentParser:
    """The parser of command `name` alone (the Python API reads its defaults)."""
    p = argparse.ArgumentParser(prog=f"isolume {name}")
    add_command_arguments(name, p)
    return p


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The argument parser with every subcommand, or with command `only` alone: a command
    line that names its command parses as it would with all of them, without importing
    the other commands' modules (0.2–0.3 s of a start; `command_named`)."""
    parser = argparse.ArgumentParser(
        prog="isolume", description="Isosurfaces with precomputed global illumination."
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for name in [only] if only is not None else [*BUILT_IN, *COMMAND_MODULES]:
        if name in BUILT_IN:
            help_text, description = BUILT_IN[name]
        else:
            module = _command_module(name)
            if module is None:
                continue
            help_text, description = module.HELP, description_of(module.HELP)
        add_command_arguments(name, sub.add_parser(name, help=help_text,
                                                   description=description))
    return parser


def command_named(words: Sequence[str]) -> str | None:
    """The command a command line's first word names, if it is one that is installed
    (else None: ``isolume``, ``isolume --help`` and a wrong name need every command)."""
    name = words[0] if words else None
    if name in BUILT_IN or (name in COMMAND_MODULES and _command_module(name) is not None):
        return name
    return None


NEGATIVE = re.compile(r"-\.?\d")
"""The start of a value that begins with a minus sign: ``-30,20``, ``-1x5``, ``-.5``."""


def _join_negative_axes(argv: Sequence[str]) -> list[str]:
    """``--up -z`` as ``--up=-z``, and an option's value that starts with a minus sign
    but is no plain number (``--view -30,20``) as ``--view=-30,20``: argparse takes such
    words for options and says the option lacks its argument. Plain negative numbers are
    left to argparse (``--iso-range -5 10``: two values)."""
    out, rest = [], list(argv)
    while rest:
        word = rest.pop(0)
        if len(word) > 2 and word.startswith("--") and "=" not in word and rest and (
                (NEGATIVE.match(rest[0]) and not _number(rest[0]))
                or (word == "--up" and rest[0] in ("-x", "-y", "-z"))):
            word = f"{word}={rest.pop(0)}"
        out.append(word)
    return out


def _number(word: str) -> bool:
    """Whether `word` reads as one number (argparse takes ``-5`` and ``-.5`` as values)."""
    try:
        float(word)
    except ValueError:
        return False
    return True


def workers_of(args: argparse.Namespace) -> int | None:
    """The threads a command may keep busy: its ``--workers``, None (also for the viewer,
    whose ``--bake-workers`` rule its bake process) for the cores this process may use
    (`cores.available`)."""
    return getattr(args, "workers", None)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``isolume`` console script; returns the exit status. Run as the
    script (`argv` None: the process ends next), it freezes the garbage collector's heap
    as it returns (`gc.freeze`): Python's finalization collects the heap several times, and
    with numba's objects in it that took ~0.2 s of every command's exit; and after a
    Ctrl-C it ends the process without waiting for pool threads (`_leave`); a Ctrl-C that
    comes while C code calls back into Python is raised after the callback
    (`volumes.interrupts`)."""
    if argv is None:
        interrupts.install()
    status = _run(argv)
    if argv is None:
        gc.freeze()
        if status == EXIT_INTERRUPTED:
            _leave(status)
    return status


FIRST_COMPILE = ("isolume: compiling the kernels for this machine (the first run only, or "
                 "after an upgrade: up to a minute on two cores; later runs load them in "
                 "about a second)")
"""What the command line says once, as numba starts compiling a kernel it found no cached
code for (a first run takes 5–10 times a later one's wall time)."""


_LISTENING: list = []
"""The listener `_say_first_compile` registered (one a process: the Python API runs
commands in the caller's process again and again)."""


def _say_first_compile() -> None:
    """Say `FIRST_COMPILE` on stderr once a process, at the first kernel numba compiles
    (not at the cached ones it loads: its ``numba:compile`` event)."""
    from numba.core import event

    if not _LISTENING:
        _LISTENING.append(_first_compile_listener())
        event.register("numba:compile", _LISTENING[0])


def _first_compile_listener() -> object:
    """A numba event listener that prints `FIRST_COMPILE` at its first event."""
    from numba.core import event

    class Once(event.Listener):
        def __init__(self) -> None:
            self.lock, self.said = threading.Lock(), False

        def on_start(self, _event: object) -> None:
            with self.lock:
                said, self.said = self.said, True
            if not said:
                print(FIRST_COMPILE, file=sys.stderr, flush=True)

        def on_end(self, _event: object) -> None:
            return None

    return Once()


def _parsed(words: list[str]) -> argparse.Namespace:
    """The options of command line `words`; words the command does not know are refused
    by its own parser (its usage, not the top level's), naming the option meant where
    one is spelled alike (`--isovalue`: `--iso`)."""
    args, unknown = build_parser(command_named(words)).parse_known_args(words)
    if unknown:
        parser = command_parser(args.command)
        options = [s for action in parser._actions for s in action.option_strings]
        meant = [close[0] for word in unknown if word.startswith("-")
                 for close in [difflib.get_close_matches(word.split("=")[0], options, 1)]
                 if close]
        hint = f" (did you mean {', '.join(dict.fromkeys(meant))}?)" if meant else ""
        parser.error(f"unrecognized arguments: {' '.join(unknown)}{hint}")
    return args


def _leave(status: int) -> None:
    """End the process now with `status`, once the command has stopped and saved what it
    finished: a pool thread may still be compiling a kernel (the first run on a machine:
    seconds, which no Ctrl-C cuts), and Python's exit would wait for it. Numba writes its
    cache files whole (to a temporary name, then renamed), so the cache stays sound."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # closed: a pipe gone, or closed on purpose
            pass
    os._exit(status)


def _run(argv: Sequence[str] | None) -> int:
    """The command `argv` names (None: the process's arguments); its exit status."""
    tune_malloc()
    words = _join_negative_axes(sys.argv[1:] if argv is None else argv)
    args = _parsed(words)
    command = COMMANDS.get(args.command) or _command_module(args.command).run
    try:
        args = apply_state(args, words[1:])  # --state FILE: the file's defaults
        if getattr(args, "timeline", None):  # written when the command ends: checked now
            from isolume.app.render.images import check_output_folder

            check_output_folder(args.timeline)
        cores.use(workers_of(args))
        if argv is None and args.command != "info":  # the console script's kernels
            blas.numba_without_blas_probe()  # before any other thread imports
            _say_first_compile()
        with cores.recording(getattr(args, "timeline", None), command=words):
            return command(args)
    except IsolumeError as exc:
        message = " ".join(str(exc).split())
        print(f"isolume: error: {message}", file=sys.stderr)
        return EXIT_USER_ERROR
    except (KeyboardInterrupt, SystemError) as exc:
        if not interrupted_by(exc):
            raise
        print("isolume: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:  # output piped into `head` and the like
        sys.stderr.close()
        return 0


if __name__ == "__main__":
    # run the imported module's main, so that command modules and this entry point share
    # one set of error classes (under `python -m`, this file is a second copy, __main__)
    from isolume.app.cli import main as _main

    sys.exit(_main())
