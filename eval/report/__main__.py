"""``python -m eval.report``: the report's command line (eval.report.cli)."""

import sys

from eval.report.cli import main
from parcelpick_env.cli import run_cli

sys.exit(run_cli(main))
