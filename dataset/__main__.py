"""``python -m dataset generate ...`` / ``python -m dataset stats ...``: the pipeline's two commands."""

from __future__ import annotations

import sys

USAGE = "usage: python -m dataset {generate,stats} [args...]"


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] not in ("generate", "stats"):
        print(USAGE, file=sys.stderr)
        return 2
    if argv[0] == "generate":
        from dataset.generate import main as run
    else:
        from dataset.stats import main as run
    from parcelpick_env.cli import run_cli

    return run_cli(run, argv[1:], prog=f"python -m dataset {argv[0]}")


if __name__ == "__main__":
    sys.exit(main())
