"""es.backend=ray on a real local Ray cluster (a head and two worker nodes, loopback only).

The cluster is started by the test with Ray's own ``ray.cluster_utils.Cluster`` (three raylets,
1 CPU each, small object stores) and torn down at the end, also on failure.
"""
import json
import os

import pytest
import torch

# Before Ray is imported: resolve this node's address to 127.0.0.1 so that nothing binds to or
# connects through another interface (Ray otherwise replaces 127.0.0.1 by the host's address).
os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
os.environ["RAY_USAGE_STATS_ENABLED"] = "0"
ray = pytest.importorskip("ray", reason="Ray is the optional extra 'ray' (included in 'dev'): pip install -e '.[dev]'")
from ray.cluster_utils import Cluster  # noqa: E402

from torchrl_esrl.envs import make_env  # noqa: E402
from torchrl_esrl.collectors.es_collector import ESCollector  # noqa: E402
from torchrl_esrl.es.openes import OpenES  # noqa: E402
from torchrl_esrl.modules.networks import flat_parameters, make_actor  # noqa: E402
from torchrl_esrl.collectors.ray_backend import member_shares  # noqa: E402

pytestmark = pytest.mark.e2e  # a Ray cluster of three raylet processes
NODE = {"num_cpus": 1, "object_store_memory": 80 * 2**20, "node_ip_address": "127.0.0.1"}


@pytest.fixture(scope="module")
def cluster():
    cluster = Cluster(initialize_head=True, head_node_args={**NODE, "include_dashboard": False})
    try:
        cluster.add_node(**NODE)
        cluster.add_node(**NODE)
        ray.init(address=cluster.address, include_dashboard=False, log_to_driver=False)
        yield cluster
    finally:
        ray.shutdown()
        cluster.shutdown()


def test_member_shares_are_contiguous_aligned_and_cover_the_population():
    assert member_shares(120, 2) == [(0, 64), (64, 120)]
    assert member_shares(120, 3) == [(0, 32), (32, 80), (80, 120)]
    for population, workers in [(6, 2), (40, 4), (120, 7), (1, 3)]:
        shares = member_shares(population, workers)
        assert len(shares) == workers and shares[0][0] == 0 and shares[-1][1] == population
        assert all(a[1] == b[0] for a, b in zip(shares, shares[1:]))
        assert all(start % 16 == 0 for start, _ in shares)


def test_ray_generation_equals_local_generation(cluster):
    actor = make_actor(17, make_env("walker2d").action_spec)
    generator = torch.Generator().manual_seed(0)
    mean = flat_parameters(actor)
    params = mean + 0.3 * torch.randn(32, mean.numel(), generator=generator)  # varied early terminations
    local = ESCollector("walker2d", actor, backend="gym", max_episode_steps=60, seed=5)
    remote = ESCollector("walker2d", actor, backend="ray", max_episode_steps=60, seed=5, address=cluster.address, num_workers=2, worker_backend="gym", num_cpus_per_worker=1)
    try:
        assert len({n["NodeID"] for n in ray.nodes() if n["Alive"]}) == 3
        assert len(set(remote.backend.nodes())) == 2  # the two actors run on different nodes
        expected, got = local.evaluate(params), remote.evaluate(params)  # same seed stream, same seeds
        es = OpenES(mean, population_size=36, sigma=0.3, generator=generator)  # 18 pairs: shares of 16 and 2 pairs
        population = es.ask()
        mirrored = es.mirrored(population)
        pairs_expected, pairs_got = local.evaluate(population, mirrored=mirrored), remote.evaluate(population, mirrored=mirrored)
    finally:
        remote.backend.close()
    assert not torch.equal(pairs_got.returns[:18], pairs_got.returns[18:])
    for key in pairs_expected.transitions.keys(True, True):  # the pairs' generation, member order and ids included
        assert torch.equal(pairs_got.transitions[key], pairs_expected.transitions[key]), key
    assert torch.equal(pairs_got.returns, pairs_expected.returns) and torch.equal(pairs_got.lengths, pairs_expected.lengths)
    assert torch.equal(got.returns, expected.returns)
    assert torch.equal(got.lengths, expected.lengths)
    assert expected.lengths.unique().numel() > 1  # some members terminated early
    assert remote.frames == local.frames == expected.frames + pairs_expected.frames
    ids = got.transitions["collector", "traj_ids"]
    assert torch.equal(ids, expected.transitions["collector", "traj_ids"])
    assert ids.max().item() == 31 and (ids[1:] >= ids[:-1]).all()  # global member indices, member order
    assert set(got.transitions.keys(True, True)) == set(expected.transitions.keys(True, True))
    for key in expected.transitions.keys(True, True):
        assert torch.equal(got.transitions[key], expected.transitions[key]), key


def test_recipe_runs_es_on_the_ray_cluster(cluster, run_recipe, tmp_path):
    result = run_recipe("es_td3.py", "iterations=1", "env=swimmer", "td3.frames_per_iteration=300", "es.backend=ray", f"ray.address='{cluster.address}'", "ray.num_workers=2", f"hydra.run.dir={tmp_path}", timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["es_frames"] == 2 * 4 * 100  # 2 generations x 4 offspring x 100 steps (Swimmer never terminates)
