"""Typed errors shared by the library and the CLIs.

Every error names what the user wrote (an argument, an option, a file and field), the bad
value, and what would be valid, so that the CLI can print it as one line.
"""

from __future__ import annotations

import re
from typing import Any


def _show(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.10g}"
    return repr(value)


class InputError(ValueError):
    """An argument of a public function is outside its valid range.

    Attributes
    ----------
    argument : str
        The argument's name as the caller wrote it, e.g. ``"focal_length_mm"``.
    value : object
        The offending value (the first bad element of an array).
    requirement : str
        What would be valid, e.g. ``"> 0"``.
    hint : str
        Optional advice on how to fix it.
    """

    def __init__(self, argument: str, value: Any, requirement: str, hint: str = ""):
        self.argument = argument
        self.value = value
        self.requirement = requirement
        self.hint = hint
        super().__init__(self.describe())

    def describe(self, names: dict[str, str] | None = None) -> str:
        """The message, with argument names replaced through ``names`` (a CLI maps them to its
        options, so that the message names what the user typed)."""
        names = names or {}
        requirement = self.requirement
        for argument, shown in names.items():  # whole words only ("out" is not in "without")
            requirement = re.sub(rf"(?<![\w-]){re.escape(argument)}(?![\w-])", shown, requirement)
        text = f"{names.get(self.argument, self.argument)} must be {requirement}, got {_show(self.value)}"
        return f"{text}; {self.hint}" if self.hint else text


class SpecError(ValueError):
    """A file people write (scene spec, stack manifest, data table) is invalid.

    The message names the file, the field (as a dotted path) and the bad value.
    """

    def __init__(self, path: str, field: str, problem: str):
        self.path = str(path)
        self.field = field
        self.problem = problem
        where = f"{self.path}: {field}" if field else self.path
        super().__init__(f"{where}: {problem}")


class OutputError(ValueError):
    """An output path cannot or may not be written (exists and is not ours, is locked by another
    run, its folder is missing). The message names the option and the path."""


class Interrupted(BaseException):
    """The process was asked to stop (SIGTERM, SIGHUP); raised by the CLIs' signal handler so
    that every writer's cleanup runs. ``exit_code`` is 128 + the signal number."""

    def __init__(self, signum: int):
        import signal

        self.signum = signum
        self.exit_code = 128 + signum
        super().__init__(f"stopped by {signal.Signals(signum).name}")
