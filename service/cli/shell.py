"""What the ``dqpose`` command owes the shell: a parser whose mistakes are answered with the usage
of the (sub)command they were made in and a did-you-mean, and a closed pipe that ends the command
quietly (``dqpose world watch | head -2``), as C tools end on SIGPIPE. Light to import."""
from __future__ import annotations

import argparse
import difflib
import os
import sys

#: exit code of a command whose standard output was closed (128 + SIGPIPE, as shells report it)
PIPE_CLOSED = 141

#: flags that were renamed: a suggestion when the old name is given where it is no alias
RENAMED = {"--target": "--server"}


def _suggestion(word: str, candidates) -> str | None:
    close = difflib.get_close_matches(word, [str(c) for c in candidates], n=1, cutoff=0.6)
    return close[0] if close else None


class Parser(argparse.ArgumentParser):
    """The parser of ``dqpose`` and, through ``add_subparsers``, of each (sub)command: an unknown
    option is an error of the deepest (sub)command, with its usage (argparse reports it with the
    top level's), and an unknown option or choice names the nearest known one (Python 3.14's
    ``suggest_on_error``, for 3.11)."""

    def parse_known_args(self, args=None, namespace=None):
        namespace, extras = super().parse_known_args(args, namespace)
        # a subcommand's parser (its prog its parent's and its name) is called by its parent's:
        # the options left over are given to it
        if extras and " " in self.prog:
            self.error(self._unrecognized(extras))
        return namespace, extras

    def _unrecognized(self, extras: list[str]) -> str:
        words = []
        for a in extras:
            flag = a.split("=", 1)[0]
            guess = None
            if flag.startswith("--"):
                guess = RENAMED.get(flag) if RENAMED.get(flag) in self._option_string_actions \
                    else _suggestion(flag, (o for o in self._option_string_actions
                                            if o.startswith("--")))
            words.append(f"{a} (did you mean {guess}?)" if guess else a)
        return "unrecognized arguments: " + " ".join(words)

    def _check_value(self, action, value):
        if action.choices is not None and value not in action.choices:
            guess = _suggestion(str(value), action.choices)
            choices = ", ".join(map(repr, action.choices))
            raise argparse.ArgumentError(
                action, f"invalid choice: {value!r} "
                + (f"(did you mean {guess!r}? choose from {choices})" if guess
                   else f"(choose from {choices})"))


class _Stdout:
    """Standard output whose closing by the reader (EPIPE) unwinds the command as Ctrl-C does:
    :class:`PipeClosed` is no ``Exception``, so no command's error handling reports it, and every
    ``with`` on the way (an arm, a client, a server) is left as it would be otherwise."""

    def __init__(self, stream):
        self._stream = stream

    def write(self, text):
        try:
            return self._stream.write(text)
        except BrokenPipeError:
            raise PipeClosed from None

    def flush(self):
        try:
            self._stream.flush()
        except BrokenPipeError:
            raise PipeClosed from None

    def __getattr__(self, name):
        return getattr(self._stream, name)


class PipeClosed(BaseException):
    """The reader of standard output went away."""


def guarded_stdout():
    """``sys.stdout`` wrapped so that a closed pipe raises :class:`PipeClosed`; returns what to
    restore."""
    before = sys.stdout
    sys.stdout = _Stdout(before)
    return before


def silence_stdout() -> None:
    """After :class:`PipeClosed`, before the process ends: standard output pointed at /dev/null,
    so that the interpreter's last flush of what is still buffered says nothing on standard
    error."""
    try:
        fd = sys.__stdout__.fileno() if sys.__stdout__ is not None else None
    except (OSError, ValueError):
        fd = None
    if fd is not None:
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, fd)
        os.close(null)
