"""What the records say about the overwrites (torchrl_esrl/report/findings.py), run by run: the
iterations the TD3 actor overwrote the ES mean, the averages that decided it, and what the two
averages reached after the last one; and the per-task summary while rows fill. Records written by
hand, each number worked out below."""
import csv
import json
from pathlib import Path

from torchrl_esrl.report import pairwise_table, results_table, summary_table, write_summary_table
from torchrl_esrl.report.findings import overwrite_runs_table, overwrite_table, write_overwrite_table
from torchrl_esrl.report.records import find_runs
from tests.test_algorithm_info import record as run_record
from tests.test_timing import ALGORITHMS


def record(folder: Path, seed: int, averages: list[tuple[float, float]], actor: float) -> None:
    """An ES-TD3Buffers run whose rule saw ``averages`` (TD3 actor's, ES mean's) per iteration."""
    folder.mkdir(parents=True)
    overwrites = sum(td3 > es for td3, es in averages)
    summary = {"env": "Walker2d-v5", "algorithm": "es_td3_buffers", "seed": seed, "ratio": [0.5, 0.2, 0.3], "buffer_mode": "multi",
               "final_return": 100.0 + seed, "final_td3_actor_return": actor, "overwrites": overwrites}
    (folder / "summary.json").write_text(json.dumps(summary))
    with (folder / "metrics.csv").open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["iteration", "td3_average", "es_average", "overwritten"])
        writer.writerows([i, td3, es, td3 > es] for i, (td3, es) in enumerate(averages))


def test_each_run_gives_its_overwritten_iterations_and_the_largest_averages_after_the_last(tmp_path):
    """Seed 0 overwrote in iterations 1 and 3 of 4: after the last, iteration 4 alone (es 900.0, td3 850.5).
    Seed 1 never did: the largest averages of the whole run (es 700.0 in iteration 2, td3 650.25 in 3).
    Seed 2 overwrote in its last iteration: nothing comes after it."""
    record(tmp_path / "s0", 0, [(300.0, 200.0), (310.0, 400.0), (1234.56, 1000.0), (850.5, 900.0)], actor=850.5)
    record(tmp_path / "s1", 1, [(100.0, 500.0), (200.0, 700.0), (650.25, 680.0)], actor=640.0)
    record(tmp_path / "s2", 2, [(100.0, 500.0), (600.0, 550.0)], actor=102.0)
    runs = find_runs([tmp_path])
    lines = overwrite_runs_table(runs, ALGORITHMS)
    assert len(lines) == 5 and len(lines[0].split("|")) == len(lines[2].split("|"))
    assert lines[2] == "| Walker2d-v5 | ES-TD3Buffers 0.5:0.2:0.3 | 0 | 1: 300.0 / 200.0; 3: 1,234.6 / 1,000.0 | 900.0 / 850.5 | 100.0 / 850.5 |"
    assert lines[3] == "| Walker2d-v5 | ES-TD3Buffers 0.5:0.2:0.3 | 1 | never | 700.0 / 650.2 | 101.0 / 640.0 |"
    assert lines[4] == "| Walker2d-v5 | ES-TD3Buffers 0.5:0.2:0.3 | 2 | 2: 600.0 / 550.0 | - (overwritten in the last iteration) | 102.0 / 102.0 |"
    out = tmp_path / "report"
    out.mkdir()
    write_overwrite_table(overwrite_table(runs, ALGORITHMS), runs, out, ALGORITHMS)
    assert (out / "overwrite_runs.md").read_text().splitlines()[2:] == lines  # the report's file: its intro, then the table
    assert "| Walker2d-v5 | ES-TD3Buffers 0.5:0.2:0.3 | 3 | 2 | 0:2 1:0 2:1 | 1 |" in (out / "overwrites.md").read_text()


def test_the_summary_names_each_row_size_once_while_rows_fill(tmp_path):
    """Rows of 1, 2 and 5 runs: the footnote lists the sizes as a series, and a row of one run is its final return."""
    runs = [run_record(algorithm, seed, 10.0 * seed) for algorithm, seeds in (("es_td3_buffers", 1), ("es_td3_shared", 2), ("td3", 5)) for seed in range(seeds)]
    rows = summary_table(runs, results_table(runs), pairwise_table(runs, ALGORITHMS), [], ALGORITHMS)
    text = write_summary_table(rows, tmp_path, ALGORITHMS).read_text()
    assert "IQM over 1, 2 or 5 runs with its 95% bootstrap CI" in text
    assert "| A | 0.0: one run |" in text
