"""What a run prints: the resolved config only when asked for, its progress, and a plain-words ending.

Progress (``logger.progress=true``) is a tqdm bar in a terminal; when the output goes to a file
(``nohup``, Slurm, CI, ``> log``) it is one plain line per iteration instead (:func:`iteration_line`),
so a log stays small and greppable. The resolved config is in the run directory anyway (Hydra's
``.hydra/config.yaml``, and every checkpoint).
"""
from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from torchrl_esrl.run.algorithm_info import AlgorithmInfo
from torchrl_esrl.run.plot import LEARNER_CURVES, RETURNED_POLICY, TD3_ACTOR


def print_config(cfg: DictConfig) -> None:
    """Print the resolved config if ``logger.print_config=true`` (called once at start-up)."""
    if cfg.logger.print_config:
        print(OmegaConf.to_yaml(cfg, resolve=True))


def returns_text(row: dict, initial_return: float | None) -> str:
    """The returns of a ``metrics.csv`` row in words: the returned policy, then each learner's."""
    learners = "".join(f", {name} {row[key]:.1f}" for key, name, _ in LEARNER_CURVES if key in row)
    initial = f" (initial {initial_return:.1f})" if initial_return is not None else ""
    return f"return {row['eval_return']:.1f}{learners}{initial}"


def iteration_line(row: dict, iterations: int, initial_return: float | None) -> str:
    """One plain line for a finished iteration (a log that is not a terminal): iteration, frames,
    returns, the overwrite decision (a run whose metrics record one) and the elapsed time."""
    seconds = int(row["wall_time_s"])
    parts = [
        f"iteration {row['iteration'] + 1}/{iterations}",
        f"TD3 frames {row['td3_frames']}",
        f"ES frames {row['es_frames']}",
        returns_text(row, initial_return),
    ]
    if "overwritten" in row:
        parts.append("ES mean overwritten" if row["overwritten"] else "ES mean kept")
    parts.append(f"elapsed {seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}")
    return " | ".join(parts)


def final_lines(summary: dict, run_dir: str | Path, info: AlgorithmInfo | None = None) -> str:
    """The last lines of a run: returns of the returned policy (named by ``info``, the recipe's),
    of the TD3 actor (a run that records one beside it), of the initial policy, whether the ES mean
    was overwritten, and where the files and the plot are."""
    run_dir = Path(run_dir)
    episodes = summary["final_episodes"]
    rows = [(f"{RETURNED_POLICY} ({info.returned})" if info else RETURNED_POLICY, summary["final_return"])]
    if "final_td3_actor_return" in summary:
        rows.append((TD3_ACTOR, summary["final_td3_actor_return"]))
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
