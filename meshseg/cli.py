"""What every `python -m meshseg.<command>` shares: the error contract and usage.

A user's mistake (a `MeshsegError`: bad file, bad setting, store not answering) ends any command with one
line `error: <message>` on stderr and exit status `ERROR_EXIT`, the status Hydra itself exits with on a bad
override, so a script sees one code for every user error of every command. Anything else is a bug and keeps
its traceback.
"""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import NoReturn

from meshseg.errors import MeshsegError

#: the exit status of every command on a user error (and on a usage error)
ERROR_EXIT = 1


def fail(message: object) -> NoReturn:
    """End the command on a user error: `error: <message>` on stderr, exit status ERROR_EXIT."""
    print(f"error: {message}", file=sys.stderr, flush=True)
    sys.exit(ERROR_EXIT)


@contextmanager
def user_errors() -> Iterator[None]:
    """A command's body under the error contract: a MeshsegError raised in it ends the command through `fail`.
    (A context, not a decorator, so that Hydra still sees the app function itself.)"""
    try:
        yield
    except MeshsegError as e:
        fail(e)


def command(fn: Callable) -> Callable:
    """A plain (not Hydra) entry point under the error contract."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with user_errors():
            return fn(*args, **kwargs)

    return wrapper


def usage(doc: str, argv: list[str]) -> None:
    """Print a command's usage and end it when asked (-h, --help: exit 0) or when given nothing (a usage error)."""
    if argv and argv[0] not in ("-h", "--help"):
        return
    print(doc.strip())
    sys.exit(0 if argv else ERROR_EXIT)
