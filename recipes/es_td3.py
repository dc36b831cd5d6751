"""ES-TD3Buffers (Callaghan, Mason and Mannion, ALA 2023), Algorithm 1, as a Hydra recipe.

    python recipes/es_td3.py env=walker2d                  # the paper's configuration
    python recipes/es_td3.py experiment=quick              # a short real run
    python recipes/es_td3.py experiment=demo learner=sac   # SAC (or DDPG) in TD3's place
    python recipes/es_td3.py -m experiment=quick 'buffer.ratio=[0.5,0.2,0.3],[0.34,0.33,0.33]'

Each run writes metrics.csv, summary.json, the TorchRL logger's files and the final actors into
its Hydra run directory, and checkpoints into its checkpoints/ folder: rerunning the command with
the same hydra.run.dir, or resume=<run dir>, continues from the last one; a finished run is left
as it is, and fresh=true starts a new one next to it (torchrl_esrl/run/lifecycle.py, docs/runs.md).
"""
from __future__ import annotations

import torch
from omegaconf import DictConfig

from torchrl_esrl.algorithm.es_phase import make_es_phase
from torchrl_esrl.algorithm.overwrite import make_overwrite_rule
from torchrl_esrl.algorithm.td3_phase import td3_phase
from torchrl_esrl.collectors.es_collector import make_es_collector
from torchrl_esrl.collectors.td3_collector import TD3EnvState, make_frame_batches
from torchrl_esrl.data.multibuffer import buffer_holdings, make_multibuffer
from torchrl_esrl.data.threshold import make_threshold
from torchrl_esrl.envs import make_train_env
from torchrl_esrl.errors import check_finite
from torchrl_esrl.es.openes import es_holdings, make_es
from torchrl_esrl.modules.networks import flat_parameters
from torchrl_esrl.objectives.learners import LEARNERS, LearnerConfig, learner_holdings, make_learner
from torchrl_esrl.run.algorithm_info import AlgorithmInfo
from torchrl_esrl.run.lifecycle import Run, recipe_main

# One name per variant (learner, buffer.mode, overwrite.mode): runs of different variants are different rows.
VARIANTS = (("buffers", "Buffers"), ("buffers_soft", "Buffers (soft overwrite)"),
            ("shared", " (one shared buffer)"), ("shared_soft", " (one shared buffer, soft overwrite)"))
ALGORITHMS = tuple(  # es_td3_buffers "ES-TD3Buffers" ... es_sac_shared_soft, in LEARNERS' order
    AlgorithmInfo(f"es_{learner}_{variant}", f"ES-{label}{suffix}", returned="ES mean", rank=10 * i + j)
    for i, (learner, label) in enumerate(LEARNERS.items()) for j, (variant, suffix) in enumerate(VARIANTS)
)


def train(cfg: DictConfig, run: Run) -> dict:
    """Algorithm 1 (paper, Section 3.3); returns the summary written to ``summary.json``.
    ``buffer.mode=shared`` is the single-buffer ablation: ES and TD3 transitions in one buffer."""
    # Initialise: TD3 actor pi, critics Q0, Q1 and targets; ES mean mu; MultiBuffer; best = -inf.
    env = make_train_env(cfg)
    td3 = make_learner(cfg, env)  # TD3, or learner=ddpg|sac in its place
    actor = td3.actor  # its deterministic policy pi: what ES searches over (SAC: the mean action)
    collector, frame_batches = make_frame_batches(cfg, env, td3)
    es, es_collector = make_es(cfg, actor), make_es_collector(cfg, actor)
    es_phase = make_es_phase(
        cfg, es, es_collector, make_multibuffer(cfg), make_threshold(cfg), on_generation=run.on_es_generation,
    )
    buffer, threshold = es_phase.buffer, es_phase.threshold  # lock-guarded when ES runs in the background
    run.progress.phase = es_phase.progress  # the ES generations under way, checkpointed between them
    overwrite = make_overwrite_rule(cfg)
    run.start(
        actor, td3=td3, exploration=td3.exploration_policy, td3_env=TD3EnvState(collector), buffer=buffer,
        es=es, es_collector=es_collector, threshold=threshold, overwrite=overwrite,
    )

    for iteration in run.iterations(algorithm(cfg).label):
        es_phase.start()  # es.schedule=async: this iteration's ES generations run alongside the TD3 phase
        # TD3: M frames of noisy actions into the noisy buffer, learning once all buffers hold K;
        # TD3 episodes raise the best return too.
        td3_stats = td3_phase(
            cfg.td3.frames_per_iteration, frame_batches, td3, buffer,
            on_episode=lambda r: threshold.observe(check_finite("TD3 episode return", r)),
            updates_per_frame=cfg.td3.updates_per_frame,
            on_batch=run.on_td3_batch if es_phase.inline else None,  # async: ES state is in flux mid-phase
            progress=run.progress.td3_phase,
        )
        td3_return = check_finite("TD3 evaluation return", run.evaluate(flat_parameters(actor)))
        # ES: g generations; offspring trajectories go to good or bad by the threshold.
        generations = es_phase.finish()
        es_return = check_finite("ES evaluation return", run.evaluate(es.mean.detach()))
        # Overwrite rule (Section 3.2): recentre ES on the TD3 actor if TD3 is ahead on average.
        decision = overwrite(td3_return, es_return)
        if decision.overwrite:
            es.set_mean(flat_parameters(actor), reset_optimizer=cfg.overwrite.reset_optimizer, mix=overwrite.mix)
        # The returned policy: mu after the rule (a soft overwrite's mean is evaluated anew).
        returned_policy_return = overwrite.mean_return(decision, lambda: run.evaluate(es.mean.detach()))
        run.log(
            iteration, run.progress.frames_now, es_collector.frames, eval_return=returned_policy_return,
            td3_updates=td3.updates, **decision.metrics(), **threshold.metrics(),
            **{f"{name}_size": size for name, size in buffer.sizes().items()}, **generations.metrics(),
            critic_loss=td3_stats["critic_loss"], actor_loss=td3_stats["actor_loss"], buffer_mode=cfg.buffer.mode,
            **td3.metrics(),  # the learner's own (SAC: its entropy temperature)
        )
    collector.shutdown()
    es_phase.close()

    # Return: mu (the paper's output), evaluated next to the TD3 actor.
    torch.save(es.mean.detach().clone(), run.run_dir / "es_mean.pt")
    torch.save(actor.state_dict(), run.run_dir / "td3_actor.pt")
    return run.finish(es.mean.detach(), {
        "ratio": list(buffer.ratio),  # (0, 0, 1) in shared mode
        "buffer_mode": cfg.buffer.mode,
        "td3_updates": td3.updates,
        "final_td3_actor_return": run.evaluate_final(flat_parameters(actor)),
        "overwrites": sum(d.overwrite for d in overwrite.decisions),
    }, alias="final_es_mean_return")


def algorithm(cfg: DictConfig) -> AlgorithmInfo:
    """The variant ``cfg`` runs: the learner, the buffer mode, then the overwrite mode."""
    learner = list(LEARNERS).index(cfg.learner.name)
    return ALGORITHMS[4 * learner + 2 * (cfg.buffer.mode == "shared") + (cfg.overwrite.mode == "soft")]


def holdings(cfg: DictConfig, sizes) -> list:
    """What :func:`train` builds: the learner, the three buffers (one in shared mode), OpenAI-ES and its generation."""
    buffers = buffer_holdings(cfg, sizes, buffers=1 if cfg.buffer.mode == "shared" else 3)
    return [*buffers, *learner_holdings(cfg, sizes), *es_holdings(cfg, sizes)]


main = recipe_main(
    train, config_name="config", algorithm=algorithm, holdings=holdings, sections={"learner": LearnerConfig},
)

if __name__ == "__main__":
    main()
