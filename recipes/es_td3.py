"""ES-TD3Buffers (Callaghan, Mason and Mannion, ALA 2023), Algorithm 1, as a Hydra recipe.

    python recipes/es_td3.py env=walker2d                  # the paper's configuration
    python recipes/es_td3.py experiment=quick              # a short real run
    python recipes/es_td3.py -m experiment=quick 'buffer.ratio=[0.5,0.2,0.3],[0.34,0.33,0.33]'

Each run writes metrics.csv, summary.json, the TorchRL logger's files and the final actors into
its Hydra run directory.
"""
from __future__ import annotations

import sys
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf
from tqdm.auto import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without installing

from torchrl_esrl.config import ConfigError, validate_config  # noqa: E402
from torchrl_esrl.factories import (  # noqa: E402
    make_actor_critic,
    make_es,
    make_es_collector,
    make_multibuffer,
    make_overwrite_rule,
    make_td3,
    make_td3_batches,
    make_threshold,
    make_train_env,
)
from torchrl_esrl.harness import RunHarness  # noqa: E402
from torchrl_esrl.metrics import METRIC_COLUMNS  # noqa: E402
from torchrl_esrl.networks import flat_parameters  # noqa: E402
from torchrl_esrl.td3 import td3_phase  # noqa: E402


def train(cfg: DictConfig, run_dir: Path) -> dict:
    """Run Algorithm 1 and return the summary written to ``summary.json``.

    ``buffer.mode=shared`` is the single-buffer ablation (ERL-style): ES and TD3 transitions
    go to one buffer, no good/bad split.
    """
    shared_buffer = cfg.buffer.get("mode", "multi") == "shared"
    harness = RunHarness(cfg, run_dir, algorithm="es_td3_shared" if shared_buffer else "es_td3_buffers", columns=METRIC_COLUMNS)

    # Initialise: TD3 actor pi, critics Q0, Q1 and targets; ES mean mu and sigma; MultiBuffer.
    env = make_train_env(cfg)
    actor, critic = make_actor_critic(cfg, env)
    td3 = make_td3(cfg, actor, critic, env.action_spec)
    collector, td3_batches = make_td3_batches(cfg, env, td3)
    buffer = make_multibuffer(cfg)
    es = make_es(cfg, actor)
    es_collector = make_es_collector(cfg, actor)
    threshold = make_threshold(cfg)  # best = -inf
    overwrite = make_overwrite_rule(cfg)
    harness.attach_actor(actor)
    evaluate = harness.evaluate  # deterministic episodes of one flat actor, the same for every recipe
    td3_frames = 0

    bar = tqdm(total=cfg.iterations, desc="ES-TD3Buffers", unit="it", disable=not cfg.logger.progress)
    for iteration in range(cfg.iterations):
        # --- TD3: M frames of noisy actions into the noisy buffer, learning once all buffers hold K.
        bar.set_postfix_str("TD3")
        td3_stats = td3_phase(
            cfg.td3.frames_per_iteration,
            td3_batches,
            td3,
            buffer,
            on_episode=threshold.observe,  # TD3 episodes raise the best return too
            updates_per_frame=cfg.td3.updates_per_frame,
        )
        td3_frames += td3_stats["frames"]
        td3_return = evaluate(flat_parameters(actor), cfg.eval.episodes)

        # --- ES: g generations; offspring trajectories go to good or bad by the threshold.
        generation_returns = []
        for generation_index in range(cfg.es.generations_per_iteration):
            bar.set_postfix_str(f"ES {generation_index + 1}/{cfg.es.generations_per_iteration}")
            population = es.ask()
            generation = es_collector.evaluate(population)
            good = threshold.route(generation.returns)
            if shared_buffer:
                buffer.extend(generation.transitions, "noisy")  # ablation: the one shared buffer
            else:
                buffer.extend(generation.transitions[generation.member_mask(good)], "good")
                buffer.extend(generation.transitions[generation.member_mask(~good)], "bad")
            es.tell(generation.returns)
            generation_returns.append(generation.returns)
        es_return = evaluate(es.mean.detach(), cfg.eval.episodes)

        # --- Overwrite rule: recentre ES on the TD3 actor if TD3 is ahead on average.
        decision = overwrite(td3_return, es_return)
        if decision.overwrite:
            es.set_mean(flat_parameters(actor), reset_optimizer=cfg.overwrite.reset_optimizer)

        all_returns = torch.cat(generation_returns) if generation_returns else torch.zeros(1)
        sizes = buffer.sizes()
        harness.log(
            iteration,
            td3_frames,
            es_collector.frames,
            # The returned policy at this checkpoint is the ES mean after the overwrite rule.
            eval_return=td3_return if decision.overwrite else es_return,
            **{
                "td3_updates": td3.updates,
                "td3_eval_return": td3_return,
                "es_eval_return": es_return,
                "td3_average": decision.td3_average,
                "es_average": decision.es_average,
                "overwritten": decision.overwrite,
                "best_return": threshold.best,
                "threshold": threshold.value,
                "good_size": sizes["good"],
                "bad_size": sizes["bad"],
                "noisy_size": sizes["noisy"],
                "es_generation_mean_return": all_returns.mean().item(),
                "es_generation_max_return": all_returns.max().item(),
                "critic_loss": td3_stats.get("critic_loss", ""),
                "actor_loss": td3_stats.get("actor_loss", ""),
                "buffer_mode": "shared" if shared_buffer else "multi",
            },
        )
        bar.update(1)
        bar.set_postfix(td3=f"{td3_return:.0f}", es=f"{es_return:.0f}", overwrite=decision.overwrite)
    bar.close()
    collector.shutdown()

    # Return: mu (the paper's output), evaluated next to the TD3 actor.
    torch.save(es.mean.detach().clone(), run_dir / "es_mean.pt")
    torch.save(actor.state_dict(), run_dir / "td3_actor.pt")
    summary = harness.finish(
        es.mean.detach(),
        {
            "ratio": list(buffer.ratio),  # (0, 0, 1) in shared mode
            "buffer_mode": "shared" if shared_buffer else "multi",
            "td3_updates": td3.updates,
            "final_td3_actor_return": evaluate(flat_parameters(actor), cfg.eval.final_episodes),
            "overwrites": sum(d.overwrite for d in overwrite.decisions),
        },
        alias="final_es_mean_return",
    )
    return summary


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
def main(cfg: DictConfig) -> None:
    try:
        validate_config(cfg)
    except ConfigError as error:
        raise SystemExit(f"config error: {error}") from None
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    print(OmegaConf.to_yaml(cfg, resolve=True)) if cfg.logger.progress else None
    summary = train(cfg, run_dir)
    print(f"final ES mean return {summary['final_es_mean_return']:.1f}, TD3 actor return {summary['final_td3_actor_return']:.1f} -> {run_dir}")


if __name__ == "__main__":
    main()
