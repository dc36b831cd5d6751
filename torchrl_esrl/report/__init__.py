"""The report over run directories (``recipes/report.py``): Table 1 of the paper per row, the
statistics of :mod:`~torchrl_esrl.report.statistics`, what the overwrites let the records say about
the buffers (:mod:`~torchrl_esrl.report.findings`), the runs' time net of holds
(:mod:`~torchrl_esrl.report.timing`), the figures, and the page's first table, the
paper's Table 1 beside our records (:mod:`~torchrl_esrl.report.overview`). What it knows of the
algorithms (labels, order, the rows it compares against) is one
:class:`~torchrl_esrl.report.records.Algorithms`, built by ``recipes/report.py``."""
from __future__ import annotations

from pathlib import Path

from torchrl_esrl.report.figures import (MAX_LINES, curve_panels, plot_aggregate, plot_buffer_sizes, plot_es_vs_td3, plot_hard_vs_soft,  # noqa: F401
                                         plot_learning_curves, plot_ratio_sweep)
from torchrl_esrl.report.findings import overwrite_table, summary_table, write_iterations, write_overwrite_table, write_summary_table  # noqa: F401
from torchrl_esrl.report.overview import overview_algorithms, overview_rows, read_paper_table, read_started, write_overview  # noqa: F401
from torchrl_esrl.report.records import Algorithms, find_runs, ratio_text, table_groups  # noqa: F401
from torchrl_esrl.report.statistics import (holm, interquartile_mean, iqm_confidence_interval, mean_band, paired_comparison,  # noqa: F401
                                            permutation_test, probability_of_improvement, smallest_called_shift)
from torchrl_esrl.report.tables import (aggregate_table, improvement_table, normalisation, normalised_scores, pairwise_table, results_table,  # noqa: F401
                                        write_aggregate_table, write_improvement_table, write_pairwise_table, write_runs_table, write_table)
from torchrl_esrl.report.timing import run_time, write_timing  # noqa: F401


def make_report(paths, out_dir, algorithms: Algorithms) -> dict:
    """Everything: the tables (csv + md) and the PNGs; returns what was written."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    runs = find_runs(paths)
    if not runs:
        raise FileNotFoundError(f"no run (summary.json + metrics.csv) under {[str(p) for p in paths]}")
    rows = results_table(runs)
    csv_path, md_path = write_table(rows, out_dir, algorithms)
    write_runs_table(runs, out_dir, algorithms)
    overwrites = overwrite_table(runs, algorithms)
    improvement = improvement_table(runs, algorithms)
    improvement_csv, improvement_md = write_improvement_table(improvement, out_dir, algorithms, overwrites=bool(overwrites))
    pairwise = pairwise_table(runs, algorithms)
    pairwise_csv, pairwise_md = write_pairwise_table(pairwise, out_dir, algorithms)
    written = {}
    if overwrites:
        written["overwrites_csv"], written["overwrites_md"] = write_overwrite_table(overwrites, runs, out_dir, algorithms)
    summary = summary_table(runs, rows, pairwise, overwrites, algorithms)
    written["summary_md"] = write_summary_table(summary, out_dir, algorithms)
    for key, path in (("iterations_md", write_iterations(runs, out_dir, algorithms)), ("timing_md", write_timing(runs, out_dir, algorithms))):
        if path is not None:
            written[key] = path
    aggregate = aggregate_table(runs, algorithms)
    if aggregate:
        written["aggregate_csv"], written["aggregate_md"] = write_aggregate_table(aggregate, runs, out_dir, algorithms)
    figures = [path for plot in (plot_learning_curves, plot_buffer_sizes, plot_es_vs_td3, plot_ratio_sweep, plot_hard_vs_soft) for path in plot(runs, out_dir, algorithms)]
    figures += plot_aggregate(aggregate, sorted(normalisation(runs, algorithms)), out_dir, algorithms)
    return {"runs": len(runs), "rows": rows, "table_csv": csv_path, "table_md": md_path, "improvement": improvement, "improvement_csv": improvement_csv,
            "improvement_md": improvement_md, "pairwise": pairwise, "pairwise_csv": pairwise_csv, "pairwise_md": pairwise_md, "overwrites": overwrites,
            "summary": summary, "aggregate": aggregate, **written, "figures": figures}


def make_overview(paths, out_dir, algorithms: Algorithms, paper_table, started=None, order=()) -> dict:
    """The overview alone (:func:`~torchrl_esrl.report.overview.write_overview`): ``paper_table`` is
    the paper's table as a CSV file (:func:`~torchrl_esrl.report.overview.read_paper_table`);
    ``started`` a file of runs started and not yet recorded (``<env id> <algorithm> <experiment>``
    a line); ``order``: the algorithms of its first rows."""
    runs = find_runs(paths)
    csv_path, md_path = write_overview(runs, out_dir, algorithms, read_paper_table(paper_table), read_started(started), order)
    return {"runs": len(runs), "overview_csv": csv_path, "overview_md": md_path, "table_md": md_path, "figures": []}
