"""One run's learning curve (``learning_curve.png``, written by every recipe at its end) and what
the report's figures share with it: the display names of the algorithms (each recipe's
:class:`~torchrl_esrl.run.algorithm_info.AlgorithmInfo`), matplotlib on the file-only Agg backend,
and the panel of one run's TD3 actor against its ES mean."""
from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

from torchrl_esrl.run.algorithm_info import AlgorithmInfo
from torchrl_esrl.run.metrics import read_metrics

# A run whose summary has ``final_td3_actor_return`` (its metrics ``td3_eval_return``) learns a TD3
# actor beside the policy it returns: the report's tables and curves show that actor as a row of its own.
TD3_ACTOR_SUFFIX = "/td3_actor"
TD3_ACTOR = "TD3 actor"  # the TD3 actor, in words (and the returned policy of a recipe that returns it)
RETURNED_POLICY = "returned policy"  # the returned policy of a run whose recipe is not known

FIGURE_DPI = 120
FONT = {"font.size": 9, "axes.titlesize": 9.5, "axes.labelsize": 9, "legend.fontsize": 8, "xtick.labelsize": 8, "ytick.labelsize": 8}


def ratio_text(summary: dict) -> str:
    """``"0.5:0.2:0.3"`` for a run with a good:bad:noisy ratio of its own (runs at different ratios
    are different configurations: never pooled); ``""`` for a run without one, or whose one shared
    buffer (``buffer_mode`` ``"shared"``) makes the ratio moot."""
    if summary.get("ratio") is None or summary.get("buffer_mode") == "shared":
        return ""
    return ":".join(f"{float(r):g}" for r in summary["ratio"])


def label(algorithm: str, ratio: str = "", algorithms: Mapping[str, AlgorithmInfo] | None = None) -> str:
    """Display name: ``<label> 0.5:0.2:0.3: its TD3 actor`` for ``<name>/td3_actor`` at that ratio
    (the label from ``algorithms``, the recipes' entries; a name it does not hold is its own label)."""
    base, actor, _ = algorithm.partition(TD3_ACTOR_SUFFIX)
    info = (algorithms or {}).get(base)
    text = (info.label if info else base) + (f" {ratio}" if ratio else "")
    return text + (": its TD3 actor" if actor else "")


def pyplot():
    """matplotlib's pyplot on the file-only Agg backend (runs and reports are headless), with the report's font sizes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.rcParams.update(FONT)
    return plt


def save_figure(fig, path: Path) -> Path:
    fig.savefig(path, dpi=FIGURE_DPI, bbox_inches="tight")
    pyplot().close(fig)
    return path


# The learners a run may evaluate beside the policy it returns: their metrics column, name and marker.
LEARNER_CURVES = (("td3_eval_return", TD3_ACTOR, "o"), ("es_eval_return", "ES mean", "s"))


def draw_es_vs_td3(ax, run: dict, returned: str = RETURNED_POLICY) -> None:
    """One run's panel: each learner's evaluation its metrics log (TD3 actor, ES mean) and the
    returned policy's (named ``returned``), unless a learner's curve is that policy's; the initial
    policy's return if recorded, overwrites as red dashed lines."""
    from matplotlib.ticker import MaxNLocator

    rows, summary = run["metrics"], run["summary"]
    iterations = [row["iteration"] for row in rows]
    logged = set(rows[0]) if rows else set()
    curves = [curve for curve in LEARNER_CURVES if curve[0] in logged]
    if returned not in {name for _, name, _ in curves}:
        curves.append(("eval_return", returned, "o" if not curves else "D"))
    for column, name, marker in curves:
        ax.plot(iterations, [row[column] for row in rows], marker=marker, markersize=3, label=name)
    if summary.get("initial_return") is not None:
        ax.axhline(summary["initial_return"], color="grey", linestyle=":", label="initial policy")
    overwritten = [row["iteration"] for row in rows if row.get("overwritten") is True]
    for i, it in enumerate(overwritten):
        ax.axvline(it, color="red", linestyle="--", alpha=0.6, label="ES mean overwritten" if i == 0 else None)
    ax.set_xlabel("iteration")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.grid(alpha=0.3)


def plot_run(run_dir, summary: dict | None = None, info: AlgorithmInfo | None = None) -> Path:
    """``learning_curve.png`` in one run directory (every recipe, at the end of its run, before
    ``summary`` is written; by default read from ``summary.json``): the deterministic evaluations
    per iteration, overwrites marked; ``info``, the recipe's, names the algorithm and its returned policy."""
    plt = pyplot()
    run_dir = Path(run_dir)
    summary = summary if summary is not None else json.loads((run_dir / "summary.json").read_text())
    run = {"summary": summary, "metrics": read_metrics(run_dir / "metrics.csv"), "dir": run_dir}
    fig, ax = plt.subplots(figsize=(6, 4))
    draw_es_vs_td3(ax, run, info.returned if info else RETURNED_POLICY)
    ax.set_ylabel("evaluation return (deterministic)")
    known = {info.name: info} if info else None
    ax.set_title(f"{summary['env']}, seed {summary['seed']}: {label(summary['algorithm'], ratio_text(summary), known)}", fontsize=10)
    ax.legend(fontsize=8, loc="best")
    return save_figure(fig, run_dir / "learning_curve.png")
