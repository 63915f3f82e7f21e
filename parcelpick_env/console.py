"""The installed commands (``[project.scripts]`` in pyproject.toml): each runs one module's ``main``.

``parcelpick-clearance ARGS`` is ``python eval/clearance.py ARGS``, with the same one-line errors
(``parcelpick_env.cli.run_cli``); the modules are imported only when their command runs.
"""

from __future__ import annotations

from importlib import import_module

from parcelpick_env.cli import run_cli

COMMANDS: dict[str, str] = {
    "parcelpick-clearance": "eval.clearance",
    "parcelpick-ap": "eval.ap",
    "parcelpick-generate": "dataset.generate",
    "parcelpick-report": "eval.report.cli",
}


def _run(command: str) -> int:
    return run_cli(import_module(COMMANDS[command]).main, prog=command)


def clearance() -> int:
    return _run("parcelpick-clearance")


def ap() -> int:
    return _run("parcelpick-ap")


def generate() -> int:
    return _run("parcelpick-generate")


def report() -> int:
    return _run("parcelpick-report")
