"""One report for every policy: offline AP (Table II, one table per quality definition, with the label oracle and
the q = 1 ceiling; what each channel costs the oracle; the paper-compatible rows), the labels-vs-physics AUC,
closed-loop clearance (Table V) and the Diffusion-Suction ablations (Tables III and IV), each beside the paper's
numbers where the paper has them, with plots and a JSON dump.

    python -m eval.report --test-data data/test --episodes 10 --out results/RESULTS.md

Every policy sees the same held-out test scenes and the same clearance seeds. A policy that cannot be
built (no checkpoint, not implemented) is listed as 'not available: <reason>'; one that fails while
being evaluated is listed as 'failed: <reason>'; neither stops the report. The numbers are whatever
the runs give: the text lists every gap to the paper as it is.

The package, a file per job:

- ``variants``: the Diffusion-Suction training runs as data (the shipped run's flags, the ablations);
- ``config``: ``ReportConfig`` and its defaults (10 clearance episodes per cell, every stored test scene);
- ``orchestration``: what is run (AP, clearance, ablations, provenance) into one plain dict;
- ``comparisons``: paired differences between methods on the same scenes and seeds;
- ``tables`` and ``figures``: the markdown tables and the matplotlib plots;
- ``markdown``: the page and the JSON dump; ``cli``: ``python -m eval.report``.
"""

from eval.report.cli import build_parser, main
from eval.report.comparisons import compare, comparisons_against, paired_ap, paired_rate
from eval.report.config import (
                                       AP_METRICS,
                                       DEFAULT_POLICIES,
                                       DIFFUSION,
                                       MIN_AP_SCENES,
                                       ReportConfig,
                                       label,
)
from eval.report.figures import plot_clearance, plot_failures, plot_precision_at_k
from eval.report.markdown import render_markdown, write_report
from eval.report.orchestration import (
                                       evaluate_ablations,
                                       evaluate_paper_compat,
                                       evaluate_policy,
                                       load_policy,
                                       provenance,
                                       read_label_physics,
                                       run_report,
                                       train_command,
)
from eval.report.tables import (
                                       ablation_comparison_table,
                                       ablation_table,
                                       channel_cost_table,
                                       comparison_table,
                                       differences,
                                       failure_table,
                                       outcome_table,
                                       paper_compat_sentences,
                                       paper_compat_table,
                                       provenance_table,
                                       table_ii,
                                       table_v,
)
from eval.report.variants import (
                                       ABLATION_TRAIN_ARGS,
                                       MAIN_TRAIN_ARGS,
                                       TRAINED_VARIANTS,
                                       TrainedVariant,
                                       train_args,
)

__all__ = ["ABLATION_TRAIN_ARGS", "AP_METRICS", "DEFAULT_POLICIES", "DIFFUSION", "MAIN_TRAIN_ARGS", "MIN_AP_SCENES",
           "TRAINED_VARIANTS", "ReportConfig", "TrainedVariant", "ablation_comparison_table", "ablation_table",
           "build_parser", "channel_cost_table", "compare", "comparison_table", "comparisons_against", "differences", "evaluate_ablations",
           "evaluate_paper_compat", "evaluate_policy", "failure_table", "label", "load_policy", "main", "outcome_table", "paired_ap",
           "paired_rate", "paper_compat_sentences", "paper_compat_table", "plot_clearance", "plot_failures", "plot_precision_at_k", "provenance",
           "provenance_table", "read_label_physics", "render_markdown", "run_report", "table_ii", "table_v", "train_args",
           "train_command", "write_report"]
