"""The Python API's keyword arguments as the commands' parsed options: one code path.

Each public function passes its keyword arguments (named as the command's options:
``--env-rotation`` is ``env_rotation``) to `namespace`, which starts from the command's
own parser defaults and stores each value as that option's parser would have, so that
the command's checks, messages and work follow unchanged.
"""

from __future__ import annotations

import argparse
import functools
import os
from collections.abc import Mapping, Sequence

from isolume.app.options import CLIError, choice_error


class OptionError(CLIError):
    """A keyword argument of the Python API that its command's option would refuse."""

JOINED = ("view", "env_rotation", "spacing", "origin", "dims")
"""Options given as comma-separated numbers (``AZ,EL``, ``X,Y,Z``): a sequence joins."""


def python_name(action: argparse.Action) -> str:
    """The keyword of a parser `action`: its long option without dashes, ``-`` as ``_``
    (``--env-rotation``: ``env_rotation``), or its positional name."""
    longest = max(action.option_strings, key=len, default=action.dest)
    return longest.lstrip("-").replace("-", "_")


@functools.cache
def _parser(command: str) -> argparse.ArgumentParser:
    from isolume.app.cli import command_parser

    return command_parser(command)


def option_actions(command: str) -> dict[str, argparse.Action]:
    """{keyword: action} of command `command`'s options (help left out; of two options
    writing one name, the one whose keyword is that name)."""
    every = [a for a in _parser(command)._actions if not isinstance(a, argparse._HelpAction)]
    names = {python_name(a) for a in every}
    actions: dict[str, argparse.Action] = {}
    for action in every:
        name = python_name(action)
        if action.const is not None and action.dest != name and action.dest in names:
            continue  # an alias such as --turntable for --kind turntable
        actions[name] = action
    return actions


def _number(value: float) -> str:
    return f"{value:g}" if isinstance(value, (int, float)) else str(value)


def option_value(name: str, value: object) -> object:
    """`value` of keyword `name` as the command's parser stores it: ``(512, 512)`` →
    ``"512x512"`` for size, a sequence of numbers → ``"30,0"`` for `JOINED` options and
    albedo, one ``--light`` spec → a list of one, a path → its text; the rest as given."""
    if value is None or isinstance(value, (bool, str)):
        return [value] if name == "light" and isinstance(value, str) else value
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if name == "size" and isinstance(value, Sequence):
        width, height = value
        return f"{int(width)}x{int(height)}"
    if name in (*JOINED, "albedo") and isinstance(value, Sequence):
        return ",".join(_number(v) for v in value)
    if name == "albedo" and isinstance(value, (int, float)):
        return _number(value)
    if name in ("light", "iso_range") and isinstance(value, Sequence):
        return list(value)
    return value


def check_choice(action: argparse.Action, name: str, value: object) -> None:
    """Raise `OptionError` when `value` is not among the choices of the option `action`
    (keyword `name`), as its parser would (`app.options.choice_error`)."""
    message = choice_error(action, name, value)
    if message is not None:
        raise OptionError(message)


def namespace(command: str, values: Mapping[str, object]) -> argparse.Namespace:
    """The parsed options of `command` given the API keywords `values` (None where the
    command's default applies is given as the default itself): the parser's defaults,
    then each value stored as its option would store it (`option_value`)."""
    parser = _parser(command)
    stored = {action.dest: action.default for action in parser._actions
              if not isinstance(action, argparse._HelpAction)}
    stored |= parser._defaults
    actions = option_actions(command)
    for name, value in values.items():
        action = actions.get(name)
        if action is not None:
            check_choice(action, name, value)
        stored[action.dest if action is not None else name] = option_value(name, value)
    stored.pop("state_parser", None)
    return argparse.Namespace(command=command, **stored)
