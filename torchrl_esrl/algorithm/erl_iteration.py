"""ERL's generations (Khadka and Tumer, "Evolution-Guided Policy Gradient in Reinforcement Learning",
NeurIPS 2018; the authors' ``run_erl.py``, ``Agent.train``), with the replay buffers they write to as a
choice: ERL's one buffer shared by the population and the learner, or ES-TD3Buffers' good, bad and
noisy buffers routed by return (Section 3.1).

One generation (:func:`erl_iteration`):

1. the GA's population, the learner's actor copied over the member that scored lowest in the
   previous generation when the sync period is due (``erl.sync_period`` generations, once the
   learner has learnt), plays ``ga.evaluations`` deterministic episodes a member:
   :func:`~torchrl_esrl.algorithm.es_phase.es_phase` with the injection as its population step,
   every episode into the shared buffer, or to good or bad by the threshold rule;
2. the GA breeds from the members' fitness (:class:`~torchrl_esrl.es.ga.GeneticAlgorithm`);
3. the learner plays one episode with its exploration policy, into the noisy buffer (the shared one);
4. once the buffer is ready, the learner takes ``td3.updates_per_frame`` updates per frame the
   generation played (the authors' ``frac_frames_train``), its own episode's included.
"""
from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import torch
from tensordict import TensorDictBase

from torchrl_esrl.algorithm.es_phase import es_phase
from torchrl_esrl.collectors.generation import population_returns
from torchrl_esrl.collectors.td3_collector import finished_episode_returns
from torchrl_esrl.errors import check_finite
from torchrl_esrl.modules.networks import flat_parameters
from torchrl_esrl.run.schema import count
from torchrl_esrl.threads import torch_threads

# What an ERL run's ``td3_frames`` count (its recipes' ``AlgorithmInfo.td3_frames``): every frame feeds the learner.
ERL_FRAMES = ("TD3 frames are every frame played: the population's fitness episodes and the learner's exploration "
              "episodes, all in its buffers (no ES frames)")
# What erl_iteration counts over the run (the run's counters).
COUNTERS = ("frames", "population_frames", "learner_frames", "injections", "injected_elites")


@dataclass
class ERLConfig:
    """The ``erl`` config section: how ERL joins its learner to its GA (the authors' ``run_erl.py``)."""

    # the learner is copied into the population every this many generations (synch_period; 1 on Hopper and Ant)
    sync_period: int = count(10)


@dataclass
class ERLProgress:
    """How far one ERL iteration has got; :func:`erl_iteration` resumes it. A recipe hands it to the
    run as ``run.progress.phase``, so that it is checkpointed at every stop point: the iteration's
    frames, member fitness, learner episode returns and losses so far, and the updates the
    generation under way still owes."""

    frames: int = 0
    returns: list[torch.Tensor] = field(default_factory=list)  # the members' fitness, one tensor a generation
    learner_returns: list[float] = field(default_factory=list)
    losses: dict[str, list[float]] = field(default_factory=dict)
    updates_left: int = 0  # > 0: a generation under way, its episodes played, its learner updates not all taken
    done: int = 0  # generations and updates over the run

    @property
    def work(self) -> int:
        """Generations and updates over the run: grows with every step (numbers the run's checkpoints)."""
        return self.done

    def position(self) -> str:
        """Where the iteration stands, in words (a stop line's)."""
        updates = f", the learner's updates under way ({self.updates_left} left)" if self.updates_left else ""
        return f"frame {self.frames} of the iteration{updates}"

    def finish_iteration(self) -> dict:
        """The iteration's columns of ``metrics.csv`` (empty where it played no generation or took no
        update); the next iteration starts from here."""
        returns = torch.cat(self.returns) if self.returns else torch.empty(0)
        learner_returns = self.learner_returns
        stats = {
            **population_returns(returns),
            "learner_episode_return": sum(learner_returns) / len(learner_returns) if learner_returns else "",
            "critic_loss": "",
            "actor_loss": "",
            **{key: sum(values) / len(values) for key, values in self.losses.items()},
        }
        self.frames, self.returns, self.learner_returns, self.losses = 0, [], [], {}
        return stats

    def state_dict(self) -> dict:
        return {
            "frames": self.frames,
            "done": self.done,
            "updates_left": self.updates_left,
            "returns": torch.cat(self.returns) if self.returns else torch.empty(0, dtype=torch.float64),
            "learner_returns": torch.tensor(self.learner_returns, dtype=torch.float64),
            "losses": {key: torch.tensor(values, dtype=torch.float64) for key, values in self.losses.items()},
        }

    def load_state_dict(self, state: dict) -> None:
        self.frames, self.done, self.updates_left = int(state["frames"]), int(state["done"]), int(state["updates_left"])
        returns = torch.as_tensor(state["returns"])
        self.returns = [returns.clone()] if returns.numel() else []
        self.learner_returns = torch.as_tensor(state["learner_returns"]).tolist()
        self.losses = {key: torch.as_tensor(values).tolist() for key, values in state["losses"].items()}


def learner_episode(frame_batches: Iterator[TensorDictBase], buffer) -> tuple[int, float]:
    """The learner's batches of frames (its collector's,
    :func:`~torchrl_esrl.collectors.td3_collector.make_frame_batches`) until one of its episodes ends,
    each into the ``noisy`` buffer; its frames and that episode's return."""
    frames = 0
    while True:
        batch = next(frame_batches)
        frames += batch.numel()
        buffer.extend(batch, "noisy")
        finished = finished_episode_returns(batch)
        if finished:
            return frames, check_finite("learner episode return", finished[0])


def erl_iteration(ga, learner, buffer, threshold, population_collector, frame_batches: Iterator[TensorDictBase],
                  counters: dict, until_frames: int, sync_period: int, updates_per_frame: float, shared_buffer: bool,
                  at: ERLProgress, stop_point: Callable[[str | Callable[[], str]], None]) -> dict:
    """Generations (module docstring) until the run has played ``until_frames`` frames; returns the
    iteration's columns (:meth:`ERLProgress.finish_iteration`).

    ``buffer``: a :class:`~torchrl_esrl.data.multibuffer.MultiBuffer`; ``shared_buffer``: every
    episode into its one buffer (``noisy``), else the population's to good or bad by ``threshold``
    (whose best return the learner's episodes raise too). ``counters`` (checkpointed with the run)
    count :data:`COUNTERS` over the run: the frames played, the population's, the learner's, the
    injections and those whose learner was one of its generation's elites. ``at``: where the
    iteration stands (a run stopped within a generation's updates resumes them); ``stop_point(where)``
    is called after every update and every generation, where the run's state is whole."""
    for key in COUNTERS:
        counters.setdefault(key, 0)
    injected: list[int] = []

    def inject(population: torch.Tensor, generation: int) -> None:
        # The authors sync after the generation whose updates it follows: due once the learner has learnt.
        if learner.updates > 0 and generation % sync_period == 0:
            injected.append(ga.inject(population, flat_parameters(learner.actor).detach().cpu()))

    while at.updates_left or counters["frames"] < until_frames:
        if not at.updates_left:  # a new generation: the population's episodes, the GA's breeding, the learner's episode
            injected.clear()
            before = population_collector.frames
            es_phase(ga, population_collector, buffer, threshold, 1, shared_buffer, population_step=inject)
            population_frames = population_collector.frames - before
            if injected:
                counters["injections"] += 1
                counters["injected_elites"] += ga.is_elite(injected[0])
            with torch_threads(learner.num_threads):
                learner_frames, episode_return = learner_episode(frame_batches, buffer)
            threshold.observe(episode_return)
            played = population_frames + learner_frames
            counters["frames"] += played
            counters["population_frames"] += population_frames
            counters["learner_frames"] += learner_frames
            at.frames += played
            at.returns.append(ga.returns.clone())
            at.learner_returns.append(episode_return)
            at.done += 1
            at.updates_left = int(played * updates_per_frame) if buffer.ready() else 0
        with torch_threads(learner.num_threads):  # the generation's updates (those left, after a resume)
            while at.updates_left:
                for key, value in learner.update(buffer.sample()).items():
                    at.losses.setdefault(key, []).append(value)
                at.updates_left -= 1
                at.done += 1
                stop_point(lambda: f"in the learner's updates after ERL generation {ga.generation}")
        stop_point(f"after ERL generation {ga.generation}")
    return at.finish_iteration()
