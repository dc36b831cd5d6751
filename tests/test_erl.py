"""ERL's generations (torchrl_esrl/algorithm/erl_iteration.py, recipes/erl.py and recipes/erl_buffers.py) on
real components: the learner copied over the weakest member every sync period, one buffer fed by the
population and the learner, or the population routed to good and bad and the learner to noisy."""
import torch
from conftest import ROOT, TINY, tiny_overrides
from hydra import compose, initialize_config_dir

from torchrl_esrl.algorithm.erl_iteration import ERLProgress, erl_iteration
from torchrl_esrl.collectors.es_collector import make_es_collector
from torchrl_esrl.collectors.td3_collector import make_frame_batches
from torchrl_esrl.data.multibuffer import make_multibuffer
from torchrl_esrl.data.threshold import make_threshold
from torchrl_esrl.envs import make_train_env
from torchrl_esrl.es.ga import make_ga
from torchrl_esrl.modules.networks import flat_parameters
from torchrl_esrl.objectives.learners import make_learner


class RecordingCollector:
    """The real population collector, keeping a copy of every population it evaluates."""

    def __init__(self, collector):
        self.collector, self.populations = collector, []

    @property
    def frames(self) -> int:
        return self.collector.frames

    def evaluate(self, params, mirrored=None):
        self.populations.append(params.clone())
        return self.collector.evaluate(params, mirrored=mirrored)


def erl_run(script: str, generations: int, *overrides: str) -> dict:
    """``generations`` ERL generations of ``recipes/<script>``'s config at the tests' budget, built as its
    ``train`` builds them; after each: the GA's population and fitness and the learner's actor."""
    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(script.removesuffix(".py"), overrides=[TINY, *tiny_overrides(script), *overrides])
    env = make_train_env(cfg)
    learner = make_learner(cfg, env)
    _, frame_batches = make_frame_batches(cfg, env, learner)
    ga = make_ga(cfg, learner.actor)
    population_collector = RecordingCollector(make_es_collector(cfg, learner.actor))
    buffer, threshold = make_multibuffer(cfg), make_threshold(cfg)
    after = []  # after each generation: (GA population, fitness, learner's actor, learner updates)

    def stop_point(where):
        if not callable(where):  # the generation's end (within the updates: a function of the words)
            learner_actor = flat_parameters(learner.actor).detach().clone()
            after.append((ga.population.clone(), ga.returns.clone(), learner_actor, learner.updates))

    counters, at, learner_returns = {}, ERLProgress(), []
    while ga.generation < generations:  # one generation a call: a budget of one frame more than played
        until = counters.get("frames", 0) + 1
        shared = cfg.buffer.mode == "shared"
        stats = erl_iteration(ga, learner, buffer, threshold, population_collector, frame_batches, counters, until,
                              cfg.erl.sync_period, cfg.td3.updates_per_frame, shared, at, stop_point)
        learner_returns.append(stats["learner_episode_return"])
    return {"ga": ga, "learner": learner, "buffer": buffer, "threshold": threshold, "counters": counters,
            "evaluated": population_collector.populations, "after": after, "learner_returns": learner_returns}


def test_the_learner_replaces_the_weakest_member_every_sync_period_and_one_buffer_holds_both_sources():
    run = erl_run("erl.py", 6, "ga.population_size=3", "erl.sync_period=2", "td3.updates_per_frame=0.02")
    after, evaluated, counters = run["after"], run["evaluated"], run["counters"]
    injected = []
    for generation in range(1, 6):  # the population evaluated after `generation` tells
        population, fitness, learner_actor, updates = after[generation - 1]
        due = updates > 0 and generation % 2 == 0
        expected = population.clone()
        if due:
            expected[int(fitness.argmin())] = learner_actor  # over the lowest-scoring member, the learner as it stood
            injected.append(generation)
        assert torch.equal(evaluated[generation], expected), generation
    assert injected == [2, 4] and counters["injections"] == 2
    # Every frame, the population's and the learner's, in the one buffer; the learner's updates per frame played.
    sizes, frames = run["buffer"].sizes(), counters["frames"]
    assert sizes["noisy"] == frames == counters["population_frames"] + counters["learner_frames"]
    assert sizes["good"] == sizes["bad"] == 0
    assert counters["population_frames"] == 6 * 3 * 100 and counters["learner_frames"] == 6 * 100  # 100-step episodes
    assert run["learner"].updates == 6 * 8  # 0.02 an update per frame, ready from the first generation's 400 frames on


def test_erl_buffers_routes_the_population_to_good_or_bad_and_the_learner_to_noisy():
    run = erl_run("erl_buffers.py", 4, "ga.population_size=4", "td3.updates_per_frame=0.02")
    sizes, counters, threshold = run["buffer"].sizes(), run["counters"], run["threshold"]
    assert sizes["good"] + sizes["bad"] == counters["population_frames"]
    assert sizes["noisy"] == counters["learner_frames"] and sizes["good"] > 0 and sizes["bad"] > 0
    # The best return is the best of every episode, the population's and the learner's.
    population_best = max(returns.max().item() for _, returns, _, _ in run["after"])
    assert threshold.best == max(population_best, *run["learner_returns"])
    assert run["learner"].updates > 0 and counters["injections"] == 3  # erl.sync_period=1 at the tests' budget


def test_the_ga_plays_the_same_generations_whichever_buffer_until_the_learner_enters_it():
    """The GA's draws and the members' episodes have streams of their own: without a sync, the buffers
    (and the learner) change nothing in the population (docs/deviations.md, ERL's frames and budget)."""
    shared = erl_run("erl.py", 3, "erl.sync_period=100")
    routed = erl_run("erl_buffers.py", 3, "erl.sync_period=100")
    assert shared["counters"]["injections"] == routed["counters"]["injections"] == 0
    assert all(torch.equal(a, b) for a, b in zip(shared["evaluated"], routed["evaluated"]))
    assert torch.equal(shared["ga"].champion, routed["ga"].champion)
    learners = (flat_parameters(run["learner"].actor) for run in (shared, routed))
    assert not torch.equal(*learners)  # the learners differ


def test_erl_buffers_learns_once_any_buffer_holds_k_and_the_strict_rule_waits_for_noisy():
    """The learner's one episode a generation is all that fills noisy: ``conf/erl_buffers.yaml`` learns from the
    buffers that hold K meanwhile (``buffer.renormalize=true``); the strict rule takes no update until noisy
    holds K (docs/deviations.md, ERL with the MultiBuffer)."""
    overrides = ("ga.population_size=4", "td3.updates_per_frame=0.02", "buffer.min_size=150", "erl.sync_period=100")
    renormalised = erl_run("erl_buffers.py", 1, *overrides)
    strict = erl_run("erl_buffers.py", 1, *overrides, "buffer.renormalize=false")
    for run in (renormalised, strict):
        sizes = run["buffer"].sizes()
        assert sizes["noisy"] == 100 < 150 <= max(sizes["good"], sizes["bad"])  # 400 population frames, 100 learner's
    assert renormalised["buffer"].renormalize and renormalised["learner"].updates == 10  # 0.02 x 500 frames
    assert strict["learner"].updates == 0
