"""What every command line shares: checks of paths and policies before any expensive work, and one-line errors.

A CLI's ``main(argv)`` calls the ``check_*`` helpers right after parsing, and its ``__main__`` line is
``sys.exit(run_cli(main))``. Any error then reaches the user as ONE line on stderr that names the argument
or file (``<prog>: error: ...``), with exit status 2 for a bad argument and 1 for a failure while running.
``--debug`` anywhere on the command line (or ``PARCELPICK_DEBUG=1``) shows the full traceback instead.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NoReturn

DEBUG_FLAG = "--debug"
DEBUG_ENV = "PARCELPICK_DEBUG"


class UsageError(ValueError):
    """A command-line argument is unusable (a path that cannot be written, a missing checkpoint, ...)."""


def one_line(exc: BaseException) -> str:
    """The exception's message on one line (h5py and torch messages span several). An error re-raised from a
    DataLoader worker carries the worker's whole traceback; only its last line, the original message, is kept."""
    text = str(exc)
    if "Original Traceback" in text:
        last = [line for line in text.splitlines() if line.strip()][-1]
        text = last.split(": ", 1)[1] if ": " in last else last
    return " ".join(text.split()) or type(exc).__name__


@contextlib.contextmanager
def _one_line_usage_errors():
    """argparse prints its whole usage block before an error; here the error alone, on one line."""
    original = argparse.ArgumentParser.error

    def error(parser: argparse.ArgumentParser, message: str) -> NoReturn:
        parser.exit(2, f"{parser.prog}: error: {' '.join(message.split())} (see --help)\n")

    argparse.ArgumentParser.error = error  # type: ignore[method-assign]
    try:
        yield
    finally:
        argparse.ArgumentParser.error = original  # type: ignore[method-assign]


def run_cli(main: Callable[[list[str]], int | None], argv: Sequence[str] | None = None,
            prog: str | None = None) -> int:
    """Run ``main`` on ``argv`` (default ``sys.argv[1:]``, ``--debug`` removed); return its exit status.

    Exceptions become one line on stderr: ``UsageError`` exits 2, anything else 1, Ctrl-C 130. argparse's own
    usage errors exit 2 as usual, but as one line without the usage block. With ``--debug`` exceptions
    propagate with tracebacks.
    """
    args = list(sys.argv[1:] if argv is None else argv)
    debug = DEBUG_FLAG in args or os.environ.get(DEBUG_ENV, "") not in ("", "0")
    args = [a for a in args if a != DEBUG_FLAG]
    spec = getattr(sys.modules.get("__main__"), "__spec__", None)  # set for `python -m package.module`
    prog = prog or (f"python -m {spec.name}" if spec is not None and spec.name else Path(sys.argv[0]).name)
    try:
        with _one_line_usage_errors():
            status = main(args)
    except KeyboardInterrupt:
        if debug:
            raise
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:
        if debug:
            raise
        print(f"{prog}: error: {one_line(exc)} (run with {DEBUG_FLAG} for a traceback)", file=sys.stderr)
        return 2 if isinstance(exc, UsageError) else 1
    return 0 if status is None else int(status) if isinstance(status, int) else 0


def usage_exit(prog: str, error: BaseException | str) -> NoReturn:
    """Print ``prog: error: ...`` as one line and exit 2, as argparse's ``parser.error`` does without the usage."""
    text = one_line(error) if isinstance(error, BaseException) else error
    print(f"{prog}: error: {text}", file=sys.stderr)
    raise SystemExit(2)


def check_output_path(path: str | os.PathLike, arg: str, *, directory: bool = False) -> Path:
    """``path`` can be written: a file (or, with ``directory``, a directory) whose folder is made here and
    proven writable by creating and removing a probe file. ``UsageError`` naming ``arg`` if not.

    Root passes ``os.access`` everywhere, including /proc, so only a real write is trustworthy.
    """
    path = Path(path)
    folder = path if directory else path.parent
    if path.exists() and (path.is_dir() != directory):
        raise UsageError(f"{arg} {path} is {'not ' if directory else ''}a directory")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(dir=folder, prefix=".parcelpick_write_test_")
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise UsageError(f"{arg} {path} cannot be written: creating a file in {folder} failed "
                         f"({exc.strerror or one_line(exc)})") from exc
    if path.exists() and not directory and not os.access(path, os.W_OK):
        raise UsageError(f"{arg} {path} exists and is not writable")
    return path


def check_input_file(path: str | os.PathLike, arg: str) -> Path:
    """``path`` is an existing, readable regular file; ``UsageError`` naming ``arg`` if not."""
    path = Path(path)
    if not path.exists():
        raise UsageError(f"{arg} {path} does not exist")
    if not path.is_file():
        raise UsageError(f"{arg} {path} is not a file")
    try:
        with open(path, "rb") as handle:
            handle.read(1)
    except OSError as exc:
        raise UsageError(f"{arg} {path} cannot be read: {exc.strerror or one_line(exc)}") from exc
    return path


def check_input_dir(path: str | os.PathLike, arg: str) -> Path:
    """``path`` is an existing directory; ``UsageError`` naming ``arg`` if not."""
    path = Path(path)
    if not path.is_dir():
        raise UsageError(f"{arg} {path} {'is not a directory' if path.exists() else 'does not exist'}")
    return path


def check_checkpoint(path: str | os.PathLike, arg: str, load: Callable[[Path], Any]) -> Any:
    """``path`` exists, is readable and ``load`` (the policy's own loader) accepts it; returns what it loaded.

    ``load``'s errors already name the file; they are re-raised as ``UsageError`` naming ``arg`` too.
    """
    path = check_input_file(path, arg)
    try:
        return load(path)
    except (ValueError, OSError, TypeError, KeyError, RuntimeError) as exc:
        raise UsageError(f"{arg} {path}: {one_line(exc)}") from exc


def check_policy_name(name: str, arg: str = "--policy") -> str:
    """``name`` is a registered policy (nothing is imported or loaded); ``UsageError`` listing them if not."""
    from policies.registry import available_policies

    if name not in available_policies():
        raise UsageError(f"{arg}: unknown policy {name!r}; choose one of {', '.join(available_policies())}")
    return name


POLICY_ARG = "--policy-arg"


def add_policy_arg(parser: argparse.ArgumentParser) -> None:
    """The evaluation commands' ``--policy-arg KEY=VALUE`` (repeatable), read with :func:`parse_policy_args`."""
    parser.add_argument(POLICY_ARG, action="append", default=[], metavar="KEY=VALUE",
                        help="a keyword for the policy's constructor, repeatable (e.g. draws=4 for Diffusion-Suction)")


def parse_policy_args(items: Sequence[str], arg: str = POLICY_ARG) -> dict[str, Any]:
    """``KEY=VALUE`` strings as keyword arguments for a policy's constructor (``draws=4``, ``decode_points=2048``,
    ``precision=bfloat16``): a value JSON reads (a number, true / false, null, a quoted string) is that value, any
    other is the string as given. ``UsageError`` naming ``arg`` for a malformed item, a repeated key or
    ``checkpoint`` (which has its own flag)."""
    import json

    out: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        key = key.strip()
        if not sep or not key.isidentifier():
            raise UsageError(f"{arg} {item!r}: expected KEY=VALUE with KEY a keyword of the policy, e.g. draws=4")
        if key == "checkpoint":
            raise UsageError(f"{arg} {item!r}: give the checkpoint with --checkpoint")
        if key in out:
            raise UsageError(f"{arg} {item!r}: {key} given twice")
        try:
            out[key] = json.loads(raw)
        except ValueError:
            out[key] = raw
    return out


def check_policy(name: str, checkpoint: str | os.PathLike | None = None, *, arg: str = "--policy",
                 checkpoint_arg: str = "--checkpoint", **kwargs: Any) -> Any:
    """Make the registered policy ``name`` (with ``checkpoint`` if given), so an unknown name, a missing or
    foreign checkpoint fails now, not in a worker after the first pile is built. Returns the policy."""
    from policies.registry import make_policy

    check_policy_name(name, arg)
    if checkpoint is not None:
        check_input_file(checkpoint, checkpoint_arg)
        kwargs["checkpoint"] = checkpoint
    try:
        return make_policy(name, **kwargs)
    except (ValueError, OSError, TypeError, KeyError, RuntimeError, ImportError, NotImplementedError) as exc:
        where = f"{checkpoint_arg} {checkpoint}" if checkpoint is not None else f"{arg} {name}"
        given = {k: v for k, v in kwargs.items() if k != "checkpoint"}
        if given:
            where += f" ({POLICY_ARG} {', '.join(f'{k}={v!r}' for k, v in given.items())})"
        raise UsageError(f"{where}: cannot make policy {name!r}: {one_line(exc)}") from exc
