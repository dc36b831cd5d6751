"""One run's learning curve (``learning_curve.png``, written by every recipe at its end) and what
the report's figures share with it: the display names of the algorithms, matplotlib on the
file-only Agg backend, and the panel of one run's TD3 actor against its ES mean."""
from __future__ import annotations

import json
from pathlib import Path

from torchrl_esrl.run.metrics import read_metrics

ALGORITHM_LABELS = {
    "es_td3_buffers": "ES-TD3Buffers",
    "es_td3_shared": "ES-TD3 (one shared buffer)",
    "td3": "TD3",
    "es": "OpenAI-ES",
    "cem_rl": "CEM-RL",
    "es_td3_buffers_soft": "ES-TD3Buffers (soft overwrite)",
    "es_td3_shared_soft": "ES-TD3 (one shared buffer, soft overwrite)",
}
ES_TD3_BUFFERS = ("es_td3_buffers", "es_td3_buffers_soft")  # runs that have a good:bad:noisy ratio
# ES-TD3 returns its ES mean, but the buffers act on its TD3 actor: the report's tables and curves
# also show that actor (``final_td3_actor_return`` / ``td3_eval_return``) as a row of its own.
TD3_ACTOR_SUFFIX = "/td3_actor"
# What each algorithm returns, for a run whose metrics have no TD3/ES columns.
RETURNED_POLICY = {"td3": "TD3 actor", "es": "ES mean", "cem_rl": "CEM mean"}

FIGURE_DPI = 120
FONT = {"font.size": 9, "axes.titlesize": 9.5, "axes.labelsize": 9, "legend.fontsize": 8, "xtick.labelsize": 8, "ytick.labelsize": 8}


def ratio_text(summary: dict) -> str:
    """``"0.5:0.2:0.3"`` for ES-TD3Buffers runs (runs at different ratios are different
    configurations: never pooled), ``""`` for every other algorithm."""
    if summary["algorithm"] not in ES_TD3_BUFFERS or summary.get("ratio") is None:
        return ""
    return ":".join(f"{float(r):g}" for r in summary["ratio"])


def label(algorithm: str, ratio: str = "") -> str:
    """Display name: ``ES-TD3Buffers 0.5:0.2:0.3: its TD3 actor`` for ``es_td3_buffers/td3_actor``."""
    base, actor, _ = algorithm.partition(TD3_ACTOR_SUFFIX)
    text = ALGORITHM_LABELS.get(base, base) + (f" {ratio}" if ratio else "")
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


def draw_es_vs_td3(ax, run: dict) -> None:
    """One run's panel: TD3 actor and ES mean per iteration (ES-TD3 runs; other algorithms: the
    returned policy), the initial policy's return if recorded, overwrites as red dashed lines."""
    from matplotlib.ticker import MaxNLocator

    rows, summary = run["metrics"], run["summary"]
    iterations = [row["iteration"] for row in rows]
    if "td3_eval_return" in rows[0]:
        ax.plot(iterations, [row["td3_eval_return"] for row in rows], marker="o", markersize=3, label="TD3 actor")
        ax.plot(iterations, [row["es_eval_return"] for row in rows], marker="s", markersize=3, label="ES mean")
    else:
        name = RETURNED_POLICY.get(summary["algorithm"], "returned policy")
        ax.plot(iterations, [row["eval_return"] for row in rows], marker="o", markersize=3, label=name)
    if summary.get("initial_return") is not None:
        ax.axhline(summary["initial_return"], color="grey", linestyle=":", label="initial policy")
    overwritten = [row["iteration"] for row in rows if row.get("overwritten") is True]
    for i, it in enumerate(overwritten):
        ax.axvline(it, color="red", linestyle="--", alpha=0.6, label="ES mean overwritten" if i == 0 else None)
    ax.set_xlabel("iteration")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.grid(alpha=0.3)


def plot_run(run_dir, summary: dict | None = None) -> Path:
    """``learning_curve.png`` in one run directory (every recipe, at the end of its run, before
    ``summary`` is written; by default read from ``summary.json``): the deterministic evaluations
    per iteration, overwrites marked."""
    plt = pyplot()
    run_dir = Path(run_dir)
    summary = summary if summary is not None else json.loads((run_dir / "summary.json").read_text())
    run = {"summary": summary, "metrics": read_metrics(run_dir / "metrics.csv"), "dir": run_dir}
    fig, ax = plt.subplots(figsize=(6, 4))
    draw_es_vs_td3(ax, run)
    ax.set_ylabel("evaluation return (deterministic)")
    ax.set_title(f"{summary['env']}, seed {summary['seed']}: {label(summary['algorithm'], ratio_text(summary))}", fontsize=10)
    ax.legend(fontsize=8, loc="best")
    return save_figure(fig, run_dir / "learning_curve.png")
