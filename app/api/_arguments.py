"""The Python API's keyword arguments as the commands' parsed options: one code path.

Each public function passes its keyword arguments (named as the command's options:
``--env-rotation`` is ``env_rotation``) to `namespace`, which starts from the command's
own parser defaults and stores each value as that option's parser would have (converted
by the option's ``type``, checked against its choices), so that the command's checks,
messages and work follow unchanged, and a value its parser would refuse is refused in one
line naming the keyword (`OptionError`).
"""

from __future__ import annotations

import argparse
import functools
import importlib
import numbers
import os
import re
from collections.abc import Mapping, Sequence

from isolume.app.options import CLIError, choice_error


class OptionError(CLIError):
    """A keyword argument of the Python API that its command's option would refuse."""

JOINED = ("view", "env_rotation", "spacing", "origin", "dims")
"""Options given as comma-separated numbers (``AZ,EL``, ``X,Y,Z``): a sequence joins."""

OBJECTS = {"volume": ("isolume.volumes.core", "Volume"),
           "lattice": ("isolume.baking.lattice", "Lattice")}
"""Keywords that take an object as well as their option's text: {keyword: (module, class)}."""

NUMBERS = {int: (numbers.Integral,), float: (numbers.Real,)}
"""The numbers an option of each ``type`` takes as they are (exactly: a float32 stays its
value); anything else is converted from its text, as the command line's would be."""

SHOWN = 80
"""The most characters of a value that a message shows."""


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


def keyword_message(command: str, message: str) -> str:
    """`message` of an error that command `command`'s code raised, its options named as
    the Python API's keywords: a leading ``--name VALUE: …`` as ``name=VALUE: …`` (the
    form of `OptionError`), every other ``--name`` of the command's as ``name``."""
    keywords = {option: python_name(action) for action in _parser(command)._actions
                for option in action.option_strings if option.startswith("--")}
    head, colon, rest = message.partition(": ")
    option, _, value = head.partition(" ")
    if colon and option in keywords and value and "--" not in value and " with " not in value:
        message = f"{keywords[option]}={value}: {rest}"
    return re.sub(r"(?<![\w-])--[a-z][a-z0-9-]*",
                  lambda m: keywords.get(m.group(0), m.group(0)), message)


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
        return "x".join(_number(v) for v in value)
    if name in (*JOINED, "albedo") and isinstance(value, Sequence):
        return ",".join(_number(v) for v in value)
    if name == "albedo" and isinstance(value, (int, float)):
        return _number(value)
    if name in ("light", "iso_range") and isinstance(value, Sequence):
        return list(value)
    return value


def shown(value: object) -> str:
    """`value`'s repr on one line, cut to `SHOWN` characters, for a message."""
    text = " ".join(repr(value).split())
    return text if len(text) <= SHOWN else f"{text[:SHOWN - 3]}..."


def _is_object(name: str, value: object) -> bool:
    """Whether `value` is the object keyword `name` takes besides text (`OBJECTS`)."""
    if name not in OBJECTS:
        return False
    module, attribute = OBJECTS[name]
    return isinstance(value, getattr(importlib.import_module(module), attribute))


def _forms(name: str) -> str:
    """What the keyword `name` takes where its option takes text."""
    if name in (*JOINED, "size", "albedo"):
        return "a str or a sequence of numbers"
    if name in OBJECTS:
        return f"a {OBJECTS[name][1]} or a path"
    return "a spec or a list of specs" if name == "light" else "a str"


def _converted(action: argparse.Action, name: str, given: object, item: object) -> object:
    """`item` (`given`, or one of its values) converted as the parser of the option
    `action` converts its text: by its ``type`` (int, float: a number, `NUMBERS`, or its
    text), else kept as text; `OptionError` naming keyword `name` and `given` where the
    parser would refuse it."""
    if action.type is None:
        if isinstance(item, str) or _is_object(name, item):
            return item
        raise OptionError(f"{name}={shown(given)}: expected {_forms(name)}")
    if isinstance(item, bool) or not isinstance(item, (str, *NUMBERS.get(action.type, ()))):
        item = str(item)  # what the command line would have: 2.5 is no int, True no number
    try:
        return action.type(item)
    except (TypeError, ValueError):
        kind = getattr(action.type, "__name__", "option")
        raise OptionError(f"{name}={shown(given)}: invalid {kind} value") from None


def converted(action: argparse.Action, name: str, given: object, value: object) -> object:
    """The value keyword `name` stores for option `action`, given `given` (`value` as
    `option_value` makes it): a flag's bool, each of a fixed number of values, each of
    the specs of an appended option, or the one value, converted (`_converted`)."""
    if given is None:
        return value
    if action.nargs == 0:
        if not isinstance(given, bool):
            raise OptionError(f"{name}={shown(given)}: expected True or False")
        return given
    if isinstance(action.nargs, int) or isinstance(action, argparse._AppendAction):
        count = action.nargs if isinstance(action.nargs, int) else None
        if not isinstance(value, list) or count not in (None, len(value)):
            expected = f"{count} values" if count else _forms(name)
            raise OptionError(f"{name}={shown(given)}: expected {expected}")
        return [_converted(action, name, given, item) for item in value]
    return _converted(action, name, given, value)


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
        if action is None:
            stored[name] = option_value(name, value)
            continue
        check_choice(action, name, value)
        stored[action.dest] = converted(action, name, value, option_value(name, value))
    stored.pop("state_parser", None)
    return argparse.Namespace(command=command, **stored)
