"""What a run prints: the resolved config only when asked for, and a plain-words ending.

The console is kept for the progress bar; the resolved config is in the run directory anyway
(Hydra's ``.hydra/config.yaml``, and every checkpoint).
"""
from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig, OmegaConf

# The policy each algorithm returns (summary.json's ``final_return``), in words.
RETURNED = {
    "es_td3_buffers": "ES mean",
    "es_td3_shared": "ES mean",
    "td3": "TD3 actor",
    "es": "ES mean",
    "cem_rl": "CEM mean",
}


def print_config(cfg: DictConfig) -> None:
    """Print the resolved config if ``logger.print_config=true`` (called once at start-up)."""
    if cfg.logger.print_config:
        print(OmegaConf.to_yaml(cfg, resolve=True))


def final_lines(summary: dict, run_dir: str | Path) -> str:
    """The last lines of a run: returns of the returned policy, of the TD3 actor (ES-TD3), of the
    initial policy, whether the ES mean was overwritten, and where the files and the plot are."""
    run_dir = Path(run_dir)
    episodes = summary["final_episodes"]
    returned = RETURNED.get(summary["algorithm"].removesuffix("_soft"), "returned policy")  # soft overwrite: the same policy
    rows = [(f"returned policy ({returned})", summary["final_return"])]
    if "final_td3_actor_return" in summary:
        rows.append(("TD3 actor", summary["final_td3_actor_return"]))
    if summary.get("initial_return") is not None:
        rows.append(("initial policy (before training)", summary["initial_return"]))
    width = max(len(name) for name, _ in rows)
    lines = [
        (
            f"{summary['algorithm']} on {summary['env']}, seed {summary['seed']}: {summary['iterations']} iterations, "
            f"{summary['td3_frames']} TD3 frames + {summary['es_frames']} ES frames, {summary['wall_time_s'] / 60:.1f} min"
        ),
        f"mean return over {episodes} deterministic episodes:",
        *(f"  {name:<{width}}  {value:9.1f}" for name, value in rows),
    ]
    if "overwrites" in summary:
        lines.append(f"the ES mean was overwritten by the TD3 actor {summary['overwrites']} time(s) in {summary['iterations']} iterations")
    lines.append(f"run files: {run_dir}  (metrics.csv, summary.json, learning curve: {run_dir / 'learning_curve.png'})")
    return "\n".join(lines)
