"""What a recipe says about its algorithm (torchrl_esrl/run/algorithm_info.py): discover() reads
every recipe's ALGORITHMS, and the report labels and orders its rows by them, so that a new
algorithm (one recipe, one config) needs no edit of the report."""
import dataclasses
from pathlib import Path

from conftest import RECIPES

from torchrl_esrl.report import Algorithms, pairwise_table, results_table, summary_table, write_summary_table, write_table
from torchrl_esrl.run.algorithm_info import AlgorithmInfo, discover

ROOT = Path(__file__).resolve().parents[1]
# The rows of the paper's report, in its order; any other recipe's rows fall in by their rank.
PAPER_REPORT_ORDER = ["es_td3_buffers", "es_td3_buffers_soft", "es_td3_shared", "es_td3_shared_soft", "td3", "cem_rl", "cem_rl_buffers", "cem_rl_buffers_shared", "es"]


def test_discover_reads_every_recipe_and_orders_the_rows_as_the_paper_report_did():
    infos = discover(ROOT / "recipes")  # recipes/report.py among them: it declares none and runs nothing on import
    order = sorted(infos, key=lambda name: Algorithms(infos).row_order((name, "")))
    assert [name for name in order if name in PAPER_REPORT_ORDER] == PAPER_REPORT_ORDER
    assert set(infos) == {info.name for module in RECIPES.values() for info in module.ALGORITHMS}  # every training recipe says what it runs
    assert "report.py" not in RECIPES and len(RECIPES) == len(list((ROOT / "recipes").glob("*.py"))) - 1  # a script that trains nothing is left out
    assert (infos["es_td3_shared_soft"].label, infos["td3"].returned, infos["cem_rl"].returned) == (
        "ES-TD3 (one shared buffer, soft overwrite)", "TD3 actor", "CEM mean")


def test_discover_finds_a_new_recipe_by_its_file_alone(tmp_path):
    (tmp_path / "my_hybrid.py").write_text(
        "from torchrl_esrl.run.algorithm_info import AlgorithmInfo\n"
        "ALGORITHMS = (AlgorithmInfo('my_hybrid', 'My Hybrid', 'hybrid mean', rank=-1),)\n"
    )
    (tmp_path / "helper.py").write_text("VALUE = 1\n")  # a module without ALGORITHMS adds nothing
    assert discover(tmp_path) == {"my_hybrid": AlgorithmInfo("my_hybrid", "My Hybrid", "hybrid mean", rank=-1)}


def record(algorithm, seed, final):
    summary = {"env": "A", "algorithm": algorithm, "seed": seed, "final_return": final, "initial_return": 0.0,
               "ratio": [0.5, 0.2, 0.3] if algorithm == "es_td3_buffers" else None}
    return {"summary": summary, "metrics": [], "dir": Path(".")}


def report_lines(runs, algorithms, out_dir):
    """The generated results.md rows and summary.md header."""
    write_table(results_table(runs), out_dir, algorithms)
    write_summary_table(summary_table(runs, results_table(runs), pairwise_table(runs, algorithms), [], algorithms), out_dir, algorithms)
    results = [line for line in (out_dir / "results.md").read_text().splitlines() if line.startswith("| A |")]
    return results, (out_dir / "summary.md").read_text().splitlines()[0]


def test_a_new_algorithm_gets_its_label_and_rank_in_the_tables_from_its_info_alone(tmp_path):
    runs = [record(name, s, base + s) for name, base in (("es_td3_buffers", 100.0), ("td3", 10.0), ("my_hybrid", 50.0)) for s in range(3)]
    known = discover(ROOT / "recipes")
    mine = AlgorithmInfo("my_hybrid", "My Hybrid", "hybrid mean", rank=-1)
    results, header = report_lines(runs, Algorithms({**known, mine.name: mine}), tmp_path)
    assert any(line.startswith("| A | My Hybrid | 3 |") for line in results)
    assert header == "| task | My Hybrid | ES-TD3Buffers 0.5:0.2:0.3 | TD3 | differences (Holm p < 0.05) |"  # rank -1: first
    results, header = report_lines(runs, Algorithms({**known, mine.name: dataclasses.replace(mine, rank=2)}), tmp_path)
    assert header == "| task | ES-TD3Buffers 0.5:0.2:0.3 | My Hybrid | TD3 | differences (Holm p < 0.05) |"  # between ranks 0 and 4
    results, header = report_lines(runs, Algorithms(known), tmp_path)  # no recipe declares it: its name, after every known row
    assert any(line.startswith("| A | my_hybrid | 3 |") for line in results)
    assert header == "| task | ES-TD3Buffers 0.5:0.2:0.3 | TD3 | my_hybrid | differences (Holm p < 0.05) |"
