"""ES-TD3Buffers (Callaghan, Mason and Mannion, ALA 2023), Algorithm 1, as a Hydra recipe.

    python recipes/es_td3.py env=walker2d                  # the paper's configuration
    python recipes/es_td3.py experiment=quick              # a short real run
    python recipes/es_td3.py -m experiment=quick 'buffer.ratio=[0.5,0.2,0.3],[0.34,0.33,0.33]'

Each run writes metrics.csv, summary.json, the TorchRL logger's files and the final actors into
its Hydra run directory, and checkpoints into its checkpoints/ folder: rerunning the command with
the same hydra.run.dir, or resume=<run dir>, continues from the last one (torchrl_esrl/run/checkpoint.py).
"""
from __future__ import annotations

import os

# Before torch loads: libgomp's default spin-wait keeps torch's OpenMP threads busy after each
# forward and steals the cores MuJoCo's batch threads need next (ES evaluation with the
# mujoco_batch backend ran its physics 2x slower; docs/performance.md). Read only at torch's
# import, hence here; setdefault so a caller's choice wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import hydra  # noqa: E402
import torch  # noqa: E402
from hydra.core.hydra_config import HydraConfig  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402
from tqdm.auto import tqdm  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without installing

from torchrl_esrl.algorithm.background_es import BackgroundES  # noqa: E402
from torchrl_esrl.collectors.td3_collector import TD3EnvState  # noqa: E402
from torchrl_esrl.run.checkpoint import RunCheckpoint, RunProgress, make_deterministic, prepare_run  # noqa: E402
from torchrl_esrl.errors import ConfigError  # noqa: E402
from torchrl_esrl.run.factories import (  # noqa: E402
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
from torchrl_esrl.errors import check_finite
from torchrl_esrl.run.faults import inject_faults_from_env  # noqa: E402
from torchrl_esrl.algorithm.es_phase import es_phase  # noqa: E402
from torchrl_esrl.run.harness import RunHarness  # noqa: E402
from torchrl_esrl.run.metrics import METRIC_COLUMNS  # noqa: E402
from torchrl_esrl.modules.networks import flat_parameters  # noqa: E402
from torchrl_esrl.run.schema import run_cli  # noqa: E402
from torchrl_esrl.algorithm.td3_phase import td3_phase  # noqa: E402


def train(cfg: DictConfig, run_dir: Path) -> dict:
    """Run Algorithm 1 and return the summary written to ``summary.json``.

    ``buffer.mode=shared`` is the single-buffer ablation (ERL-style): ES and TD3 transitions
    go to one buffer, no good/bad split.
    """
    shared_buffer = cfg.buffer.mode == "shared"
    progress = RunProgress()  # iteration, TD3 frames, the TD3 phase under way, the resumable clock
    harness = RunHarness(cfg, run_dir, algorithm=("es_td3_shared" if shared_buffer else "es_td3_buffers") + ("_soft" if cfg.overwrite.mode == "soft" else ""), columns=METRIC_COLUMNS, clock=progress.wall_time)
    make_deterministic()

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
    background_es = None
    if cfg.mode == "async":  # ES generations overlap the TD3 phase; buffer and threshold become lock-guarded
        background_es, buffer, threshold = BackgroundES.wrap(es, es_collector, buffer, threshold, cfg.es.generations_per_iteration, shared_buffer)
    harness.attach_actor(actor)
    evaluate = harness.evaluate  # deterministic episodes of one flat actor, the same protocol for every recipe
    components = dict(progress=progress, td3=td3, exploration=td3.exploration_policy, td3_env=TD3EnvState(collector), buffer=buffer, es=es, es_collector=es_collector, evaluator=harness.evaluator, threshold=threshold, overwrite=overwrite)
    checkpoint = RunCheckpoint(run_dir, OmegaConf.to_container(cfg, resolve=True), cfg.checkpoint.every_frames, cfg.checkpoint.keep_last, **components)
    checkpoint.restore()  # continue from the run directory's last checkpoint, if it has one
    inject_faults_from_env(progress, es, buffer)  # tests only: ESRL_INJECT_NAN=<where>@<iteration>

    bar = tqdm(total=cfg.iterations, desc="ES-TD3Buffers", unit="it", disable=not cfg.logger.progress)
    for iteration in range(progress.iteration, cfg.iterations):
        # --- TD3: M frames of noisy actions into the noisy buffer, learning once all buffers hold K.
        bar.set_postfix_str("TD3")
        if background_es is not None:
            background_es.start()  # this iteration's ES generations, from the current mean, in a thread
        td3_stats = td3_phase(
            cfg.td3.frames_per_iteration,
            td3_batches,
            td3,
            buffer,
            on_episode=lambda r: threshold.observe(check_finite("TD3 episode return", r)),  # TD3 episodes raise the best too
            updates_per_frame=cfg.td3.updates_per_frame,
            on_batch=checkpoint.maybe_save_mid_phase if background_es is None else None,  # every checkpoint.every_frames frames (async: ES state is in flux, iteration boundaries only)
            progress=progress.td3_phase,
        )
        td3_frames = progress.td3_frames + td3_stats["frames"]
        generation_returns = background_es.join() if background_es is not None else []  # async: ES ran alongside
        td3_return = check_finite("TD3 evaluation return", evaluate(flat_parameters(actor), cfg.eval.episodes))

        # --- ES: g generations; offspring trajectories go to good or bad by the threshold (async: done above).
        if background_es is None:
            generation_returns = es_phase(
                es,
                es_collector,
                buffer,
                threshold,
                cfg.es.generations_per_iteration,
                shared_buffer=shared_buffer,
                on_generation=lambda g: bar.set_postfix_str(f"ES {g + 1}/{cfg.es.generations_per_iteration}"),
            )
        es_return = check_finite("ES evaluation return", evaluate(es.mean.detach(), cfg.eval.episodes))

        # --- Overwrite rule: recentre ES on the TD3 actor if TD3 is ahead on average.
        decision = overwrite(td3_return, es_return)
        if decision.overwrite:
            es.set_mean(flat_parameters(actor), reset_optimizer=cfg.overwrite.reset_optimizer, mix=overwrite.mix)

        all_returns = torch.cat(generation_returns) if generation_returns else torch.zeros(1)
        sizes = buffer.sizes()
        harness.log(
            iteration,
            td3_frames,
            es_collector.frames,
            # The policy returned at this point is the ES mean after the overwrite rule (soft: evaluated anew).
            eval_return=es_return if not decision.overwrite else td3_return if overwrite.mix == 1 else evaluate(es.mean.detach(), cfg.eval.episodes),
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
                "buffer_mode": cfg.buffer.mode,
            },
        )
        progress.finish_iteration(td3_frames)
        checkpoint.save()
        bar.update(1)
        bar.set_postfix(td3=f"{td3_return:.0f}", es=f"{es_return:.0f}", overwrite=decision.overwrite)
    bar.close()
    collector.shutdown()
    if background_es is not None:
        background_es.close()

    # Return: mu (the paper's output), evaluated next to the TD3 actor.
    torch.save(es.mean.detach().clone(), run_dir / "es_mean.pt")
    torch.save(actor.state_dict(), run_dir / "td3_actor.pt")
    summary = harness.finish(
        es.mean.detach(),
        {
            "ratio": list(buffer.ratio),  # (0, 0, 1) in shared mode
            "buffer_mode": cfg.buffer.mode,
            "td3_updates": td3.updates,
            "final_td3_actor_return": harness.evaluate_final(flat_parameters(actor)),
            "overwrites": sum(d.overwrite for d in overwrite.decisions),
        },
        alias="final_es_mean_return",
    )
    return summary


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
def main(cfg: DictConfig) -> None:
    try:
        cfg, run_dir = prepare_run(cfg, HydraConfig.get().runtime.output_dir)  # checks; the saved config on resume
    except ConfigError as error:
        raise SystemExit(f"config error: {error}") from None
    print(OmegaConf.to_yaml(cfg, resolve=True)) if cfg.logger.progress else None
    try:
        summary = train(cfg, run_dir)
    except FloatingPointError as fault:
        raise SystemExit(f"numerical fault: {fault}; run stopped, last good checkpoint kept in {run_dir / 'checkpoints'}") from None
    print(f"final ES mean return {summary['final_es_mean_return']:.1f}, TD3 actor return {summary['final_td3_actor_return']:.1f} -> {run_dir}")


if __name__ == "__main__":
    run_cli(main)  # configuration errors as one line, no traceback
