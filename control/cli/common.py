"""Shared command-line plumbing: one ``error:`` line and exit 2 for bad input, JSON output.

Exit status: 0 done; 2 bad input (one line ``error: ...`` on stderr, no traceback); 1 an
internal failure (traceback on stderr); 130 interrupted.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import json
import signal
import sys
import threading
import traceback
from collections.abc import Callable, Iterator, Sequence
from typing import Any, NoReturn

import numpy as np

from pneutune.control.errors import PneutuneError, command_message


class ArgumentParser(argparse.ArgumentParser):
    """argparse with the project's error format: one ``error:`` line, exit status 2."""

    def error(self, message: str) -> NoReturn:
        sys.stderr.write(f"error: {self.prog}: {message} (see {self.prog} --help)\n")
        raise SystemExit(2)


def make_parser(prog: str, description: str, epilog: str = "") -> ArgumentParser:
    """A parser whose help keeps the formatting of ``description`` and ``epilog``."""
    return ArgumentParser(prog=prog, description=description, epilog=epilog,
                          formatter_class=argparse.RawDescriptionHelpFormatter)


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return _jsonable(obj.item())
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def print_json(obj: Any) -> None:
    """Print exactly one JSON object on stdout (non-finite numbers become null)."""
    sys.stdout.write(json.dumps(_jsonable(obj), allow_nan=False) + "\n")
    sys.stdout.flush()


def info(message: str) -> None:
    """Prose for the user: always on stderr, so stdout stays clean for --json."""
    sys.stderr.write(message + "\n")


@contextlib.contextmanager
def first_interrupt_only(note: str) -> Iterator[None]:
    """Inside the block the first Ctrl-C raises KeyboardInterrupt as usual, and later ones print
    ``note`` and are otherwise ignored: the run that caught the first one closes its valves and
    writes its log without a second Ctrl-C losing them.

    Outside the main thread, or where SIGINT is ignored (a background job), nothing changes.

    Parameters
    ----------
    note : str
        What a second Ctrl-C is told (one line on stderr).
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.getsignal(signal.SIGINT)
    if previous is signal.SIG_IGN:
        yield
        return
    count = 0

    def handler(signum: int, frame: Any) -> None:
        nonlocal count
        count += 1
        if count == 1:
            raise KeyboardInterrupt
        sys.stderr.write(note + "\n")

    signal.signal(signal.SIGINT, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def caused_by_interrupt(exc: BaseException) -> bool:
    """Whether ``exc`` was raised while a KeyboardInterrupt was being handled (anywhere in its
    chain of causes and contexts): Optuna, for one, can fail in its own clean-up when a Ctrl-C
    arrives inside it, and that failure is the interrupt, not a bug."""
    seen: set[int] = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        if isinstance(cur, KeyboardInterrupt):
            return True
        seen.add(id(cur))
        # the chain Python prints: the cause, else the context unless `from None` hid it
        cur = cur.__cause__ if cur.__cause__ is not None else (
            None if cur.__suppress_context__ else cur.__context__)
    return False


def run_cli(main: Callable[[Sequence[str] | None], int | None],
            argv: Sequence[str] | None = None) -> NoReturn:
    """Run a command's ``main`` and turn its failures into the exit-status contract.

    Parameters
    ----------
    main : callable
        The command's ``main(argv)``; its return value is the exit status (None: 0).
    argv : sequence of str, optional
        The arguments; None (a console script) reads ``sys.argv``.

    Notes
    -----
    A console script (``argv`` None) first moves every object its imports made (numba's and
    LLVM's typing tables, the modules) into the collector's permanent generation
    (``gc.freeze``): the cyclic collector then never walks them again, neither during the run
    nor when the interpreter exits. On ``tune --trials 200`` that is about 0.7 s of a 43 s run
    (docs/tuning.md, "Speed"); no number changes. A call with ``argv`` (tests, other Python
    code) leaves its process's collector alone.
    """
    if argv is None:
        gc.freeze()
    try:
        code = main(argv)
    except PneutuneError as exc:
        sys.stderr.write(f"error: {command_message(exc)}\n")
        raise SystemExit(2) from None
    except KeyboardInterrupt:
        sys.stderr.write("error: interrupted\n")
        raise SystemExit(130) from None
    except SystemExit:
        raise
    except Exception as exc:
        if caused_by_interrupt(exc):  # a library that failed while a Ctrl-C went through it
            sys.stderr.write("error: interrupted\n")
            raise SystemExit(130) from None
        # an internal failure: show everything
        traceback.print_exc()
        sys.stderr.write("error: internal failure (a bug in pneutune; the traceback is above)\n")
        raise SystemExit(1) from None
    raise SystemExit(0 if code is None else int(code))


