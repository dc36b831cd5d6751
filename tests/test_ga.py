"""ERL's genetic algorithm (Khadka and Tumer 2018; the authors' SSNE): selection, elitism, crossover,
mutation, the learner's injection, determinism and exact resume."""
import math

import pytest
import torch

from torchrl_esrl.envs import make_env
from torchrl_esrl.es.ga import GeneticAlgorithm, _in_rounds, initial_population, parameter_shapes
from torchrl_esrl.modules.networks import flat_parameters, load_flat_parameters, make_actor

SHAPES = [torch.Size([8, 3]), torch.Size([8]), torch.Size([2, 8]), torch.Size([2])]  # a 3-8-2 MLP
D = sum(s.numel() for s in SHAPES)


def ga(size=10, seed=0, **operators):
    population = torch.randn(size, D, generator=torch.Generator().manual_seed(100 + seed))
    return GeneticAlgorithm(population, SHAPES, generator=torch.Generator().manual_seed(seed), **operators)


def quadratic(population):
    """A deterministic fitness: the closer to 0.5 everywhere, the better."""
    return -((population - 0.5) ** 2).sum(1).double()


def layer(row, index):
    offset = sum(s.numel() for s in SHAPES[:index])
    return row[offset : offset + SHAPES[index].numel()].view(SHAPES[index])


def test_for_actor_builds_fresh_actors_of_the_actor_layout_from_its_generator_alone():
    actor = make_actor(8, make_env("swimmer").action_spec, (16, 16))
    global_state = torch.random.get_rng_state()
    first = GeneticAlgorithm.for_actor(actor, 6, torch.Generator().manual_seed(4))
    assert torch.equal(torch.random.get_rng_state(), global_state)  # every draw from the GA's generator
    again = GeneticAlgorithm.for_actor(actor, 6, torch.Generator().manual_seed(4))
    other = GeneticAlgorithm.for_actor(actor, 6, torch.Generator().manual_seed(5))
    assert first.population.shape == (6, flat_parameters(actor).numel())
    assert torch.equal(first.population, again.population) and not torch.equal(first.population, other.population)
    assert len({tuple(row.tolist()) for row in first.population}) == 6  # six different actors
    assert parameter_shapes(actor) == [p.shape for p in actor.parameters()]
    # PyTorch's default Linear initialisation: U(-1/sqrt(fan_in), 1/sqrt(fan_in)), here fan_in 8 for the first layer
    load_flat_parameters(actor, first.population[3].clone())
    first_weight = next(actor.parameters())
    assert first_weight.abs().max() <= 1 / math.sqrt(8) and first_weight.std() > 0.5 / math.sqrt(8 * 3)
    with pytest.raises(ValueError, match="reset_parameters"):
        initial_population(torch.nn.Tanh(), 2, torch.Generator())


def test_the_elites_survive_unchanged_and_the_champion_is_the_best_member_as_evaluated():
    algorithm = ga(elite_fraction=0.2)
    assert algorithm.num_elites == 2
    population = algorithm.ask()
    returns = quadratic(population)
    new_elites = algorithm.tell(population, returns)
    best = returns.argsort(descending=True)[:2]
    assert len(new_elites) == 2
    for row, member in zip(new_elites.tolist(), best.tolist()):
        assert torch.equal(algorithm.population[row], population[member])  # copied, then spared by every operator
    assert torch.equal(algorithm.champion, population[best[0]]) and torch.equal(algorithm.mean, algorithm.champion)
    assert algorithm.generation == 1


def test_with_elitism_the_best_return_never_falls_on_a_deterministic_fitness():
    algorithm = ga(seed=3)
    best = []
    for _ in range(25):
        population = algorithm.ask()
        returns = quadratic(population)
        algorithm.tell(population, returns)
        best.append(returns.max().item())
    assert all(later >= earlier for earlier, later in zip(best, best[1:]))
    assert best[-1] > best[0]  # and the population improves


def test_crossover_copies_whole_rows_and_elements_either_way_in_the_expected_share():
    algorithm = ga()
    into_first = into_second = 0
    trials = 400
    for _ in range(trials):
        first, second = torch.zeros(D), torch.ones(D)
        algorithm.crossover(first, second)
        for index, shape in enumerate(SHAPES):
            a, b = layer(first, index), layer(second, index)
            if len(shape) == 2:  # whole rows (a neuron's incoming weights), never part of one
                assert torch.all((a == a[:, :1]).all(1)) and torch.all((b == b[:, :1]).all(1))
            a_rows, b_rows = (a[:, 0], b[:, 0]) if len(shape) == 2 else (a, b)
            assert not torch.any((a_rows == 1) & (b_rows == 0))  # a copied row: both members hold it alike
            if index == 0:
                into_first += int((a_rows == 1).sum())
                into_second += int((b_rows == 0).sum())
    rows = SHAPES[0][0]  # 8 rows, U{0..15} copies of a random row each
    touched = sum(1 - (1 - 1 / rows) ** c for c in range(2 * rows)) / (2 * rows)
    expected = trials * rows * touched / 2  # half of the touched rows each way
    for observed in (into_first, into_second):
        assert abs(observed - expected) < 5 * math.sqrt(expected), (observed, expected)


def _sequential_mutation(algorithm, member, state):
    """The mutation rule applied one draw at a time, in draw order, replaying the GA's generator from
    ``state``; returns how many draws hit an entry drawn before."""
    repeated = 0
    g = torch.Generator()
    g.set_state(state)
    chances = 2 * torch.rand(len(SHAPES), generator=g)
    offset = 0
    for shape, chance in zip(SHAPES, chances.tolist()):
        n = shape.numel()
        if len(shape) == 2 and float(torch.rand(1, generator=g)) < chance:
            count = int(torch.randint(math.ceil(algorithm.mutation_fraction * n), (1,), generator=g))
            if count:
                entries = torch.randint(n, (count,), generator=g)
                repeated += count - len(entries.unique())
                kind, noise = torch.rand(count, generator=g), torch.randn(count, generator=g)
                for entry, u, z in zip(entries.tolist(), kind.tolist(), noise.tolist()):
                    w = member[offset + entry]
                    if u < algorithm.super_mutation_prob:
                        w = w + algorithm.super_mutation_strength * w * z
                    elif u < algorithm.super_mutation_prob + algorithm.reset_prob:
                        w = torch.tensor(z)
                    else:
                        w = w + algorithm.mutation_strength * w * z
                    member[offset + entry] = w.clamp(-algorithm.weight_limit, algorithm.weight_limit)
        offset += n
    return repeated


def test_mutation_is_the_rule_applied_draw_by_draw_repeated_entries_included():
    algorithm = ga(mutation_fraction=1.0, super_mutation_prob=0.3, reset_prob=0.3, weight_limit=2.0)  # many repeats, clamps
    repeats = 0
    for trial in range(30):
        member = torch.randn(D, generator=torch.Generator().manual_seed(trial))
        expected, state = member.clone(), algorithm.generator.get_state()
        repeats += _sequential_mutation(algorithm, expected, state)
        algorithm.mutate(member)
        assert torch.equal(member, expected)
    assert repeats > 0  # entries drawn twice were among them: their draw order mattered


def test_rounds_apply_each_entry_draws_in_draw_order():
    rounds = _in_rounds(torch.tensor([3, 1, 3, 3, 1, 2]))
    assert [r.nonzero().flatten().tolist() for r in rounds] == [[0, 1, 5], [2, 4], [3]]


def test_mutation_statistics_biases_untouched_normal_steps_proportional_to_the_weight():
    algorithm = ga(super_mutation_prob=0.0, reset_prob=0.0)
    steps, changed_layers, mutated = [], 0, 0
    for _ in range(300):
        member = torch.full((D,), 0.5)
        algorithm.mutate(member)
        assert torch.all(layer(member, 1) == 0.5) and torch.all(layer(member, 3) == 0.5)  # biases are not mutated
        for index in (0, 2):
            weights = layer(member, index).flatten()
            moved = weights != 0.5
            assert int(moved.sum()) <= math.ceil(0.1 * weights.numel()) - 1
            changed_layers += bool(moved.any())
            mutated += 1
            steps.append((weights[moved] - 0.5) / 0.05)  # w + N(0, (0.1 w)^2): (w' - w) / (0.1 w) ~ N(0, 1)
    z = torch.cat(steps)
    assert abs(z.mean()) < 0.15 and 0.85 < z.std() < 1.15
    # layer chosen with probability E[min(1, 2u)] = 3/4, then U{0..ceil(0.1 n)-1} mutations (layer 0: 0..2, layer 2: 0..1)
    assert 0.3 < changed_layers / mutated < 0.6


def test_resets_draw_fresh_standard_normal_weights_and_every_mutation_is_clamped():
    algorithm = ga(super_mutation_prob=0.0, reset_prob=1.0, mutation_fraction=1.0)
    values = []
    for _ in range(200):
        member = torch.full((D,), 1e3)
        algorithm.mutate(member)
        values.append(member[member != 1e3])
    z = torch.cat(values)
    assert abs(z.mean()) < 0.1 and 0.9 < z.std() < 1.1
    clamped = ga(super_mutation_prob=1.0, reset_prob=0.0, mutation_fraction=1.0, weight_limit=100.0)
    member = torch.full((D,), 90.0)
    for _ in range(20):
        clamped.mutate(member)
    assert member.abs().max() == 100.0  # super mutations (w += N(0, (10 w)^2)) reach the limit and stop there


def test_the_same_generator_gives_the_same_generations():
    def run(seed):
        algorithm = ga(seed=seed)
        for _ in range(4):
            population = algorithm.ask()
            algorithm.tell(population, quadratic(population))
        return algorithm.population

    assert torch.equal(run(0), run(0)) and not torch.equal(run(0), run(1))


def test_a_state_dict_taken_mid_run_resumes_to_the_same_next_generation(tmp_path):
    algorithm = ga(seed=2, elite_fraction=0.2)
    for _ in range(2):
        population = algorithm.ask()
        algorithm.tell(population, quadratic(population))
    torch.save(algorithm.state_dict(), tmp_path / "ga.pt")
    population = algorithm.ask()
    algorithm.tell(population, quadratic(population))

    resumed = ga(seed=9, elite_fraction=0.2)  # another generator and population: the state replaces both
    resumed.load_state_dict(torch.load(tmp_path / "ga.pt", weights_only=True))
    assert resumed.generation == 2
    again = resumed.ask()
    assert torch.equal(again, population)
    resumed.tell(again, quadratic(again))
    assert torch.equal(resumed.population, algorithm.population) and resumed.generation == 3
    assert resumed.weakest() == algorithm.weakest() and torch.equal(resumed.champion, algorithm.champion)
    assert torch.equal(resumed.generator.get_state(), algorithm.generator.get_state())
    with pytest.raises(ValueError, match="shape"):
        ga(size=4).load_state_dict(algorithm.state_dict())


def test_injection_replaces_the_member_that_scored_lowest_and_the_ga_breeds_from_it():
    algorithm = ga(seed=1)
    with pytest.raises(RuntimeError, match="no generation"):
        algorithm.weakest()
    population = algorithm.ask()
    returns = quadratic(population)
    algorithm.tell(population, returns)
    assert algorithm.weakest() == int(returns.argmin())
    learner = torch.full((D,), 0.5)  # the best possible member of this fitness
    asked = algorithm.ask()
    before = asked.clone()
    row = algorithm.inject(asked, learner)
    assert row == int(returns.argmin()) and torch.equal(asked[row], learner)
    others = torch.arange(10) != row
    assert torch.equal(asked[others], before[others])
    algorithm.tell(asked, quadratic(asked))  # told the population as evaluated, the learner in it
    assert torch.equal(algorithm.champion, learner)


def test_bad_settings_are_refused_naming_the_field():
    with pytest.raises(ValueError, match="ga.elite_fraction"):
        ga(elite_fraction=0.6)
    with pytest.raises(ValueError, match="ga.mutation_prob"):
        ga(mutation_prob=1.5)
    with pytest.raises(ValueError, match="ga.population_size"):
        ga(size=1)
    with pytest.raises(ValueError, match="weight matrices"):
        GeneticAlgorithm(torch.zeros(4, 18), [torch.Size([2, 3, 3])])
    with pytest.raises(ValueError, match="hold 50 parameters, a population row 51"):
        GeneticAlgorithm(torch.zeros(4, 51), SHAPES)
    algorithm = ga()
    with pytest.raises(ValueError, match="expected 10 returns"):
        algorithm.tell(algorithm.ask(), torch.zeros(9))
    with pytest.raises(FloatingPointError, match="non-finite"):
        algorithm.tell(algorithm.ask(), torch.full((10,), float("nan")))


def test_each_member_plays_its_evaluations_and_its_fitness_is_their_mean():
    algorithm = ga(size=4, seed=3, evaluations=3, elite_fraction=0.25)
    population = algorithm.ask()
    assert population.shape == (12, D)
    assert torch.equal(population[0:3], algorithm.population[0].expand(3, D)) and torch.equal(population[9:12], algorithm.population[3].expand(3, D))
    returns = torch.tensor([1.0, 2.0, 3.0, 9.0, 9.0, 9.0, -5.0, 0.0, 2.0, 4.0, 4.0, 4.0], dtype=torch.float64)  # means 2, 9, -1, 4
    algorithm.tell(population, returns)
    assert algorithm.returns.tolist() == [2.0, 9.0, -1.0, 4.0]
    assert torch.equal(algorithm.champion, population[3]) and algorithm.weakest() == 2
    assert algorithm.is_elite(1) and not algorithm.is_elite(3)
    asked = algorithm.ask()
    learner = torch.full((D,), 0.25)
    assert algorithm.inject(asked, learner) == 2
    assert torch.equal(asked[6:9], learner.expand(3, D))  # all three rows of the weakest member
    algorithm.tell(asked, torch.zeros(12))
    one_row = algorithm.ask()
    one_row[0] += 1.0
    with pytest.raises(ValueError, match="a member's rows differ"):
        algorithm.tell(one_row, torch.zeros(12))


def test_the_ga_section_refuses_what_the_ga_would_in_one_line_naming_the_key():
    from omegaconf import OmegaConf

    from torchrl_esrl.errors import ConfigError
    from torchrl_esrl.es.ga import GAConfig, make_ga

    section = OmegaConf.structured(GAConfig)
    GAConfig.check(section, "ga")  # the authors' values pass
    with pytest.raises(ConfigError, match=r"^ga.elite_fraction: 0.6 .*allowed"):
        GAConfig.check(OmegaConf.merge(section, {"elite_fraction": 0.6}), "ga")
    with pytest.raises(ConfigError, match=r"^ga.reset_prob: .*allowed"):
        GAConfig.check(OmegaConf.merge(section, {"super_mutation_prob": 0.5, "reset_prob": 0.6}), "ga")
    actor = make_actor(8, make_env("swimmer").action_spec, (16, 16))
    cfg = OmegaConf.create({"seed": 4, "ga": OmegaConf.merge(section, {"population_size": 6, "evaluations": 2})})
    built = make_ga(cfg, actor)
    assert built.ask().shape == (12, flat_parameters(actor).numel()) and built.num_elites == 1
    assert torch.equal(built.population, GeneticAlgorithm.for_actor(actor, 6, torch.Generator().manual_seed(5)).population)  # seed + 1
