"""Runs the real recipes/es_td3.py with a NaN injected on purpose, for the fault tests:

    python tests/inject_nan.py <where>@<iteration> <hydra overrides...>

``where``: ``td3_batch`` (the reward of the first item of a TD3 batch: the critic loss turns
NaN), ``es_return`` (the first offspring return handed to ``OpenES.tell``) or ``es_mean`` (the
ES mean right after ``OpenES.tell``), in iteration ``iteration``.
"""
import importlib.util
import sys
from pathlib import Path

import torch

from torchrl_esrl.run.lifecycle import Run

RECIPE = Path(__file__).resolve().parents[1] / "recipes" / "es_td3.py"
WHERE = ("td3_batch", "es_return", "es_mean")


def load_recipe():
    spec = importlib.util.spec_from_file_location("es_td3", RECIPE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def main(spec: str, overrides: list[str]) -> None:
    where, _, at = spec.partition("@")
    if where not in WHERE or not at.isdigit():
        raise SystemExit(f"usage: inject_nan.py <{'|'.join(WHERE)}>@<iteration> <overrides>, got {spec!r}")
    current = {"iteration": -1}
    iterations = Run.iterations

    def counted(self, desc):
        for iteration in iterations(self, desc):
            current["iteration"] = iteration
            yield iteration

    Run.iterations = counted

    def active() -> bool:
        return current["iteration"] == int(at)

    recipe = load_recipe()
    make_multibuffer, make_es = recipe.make_multibuffer, recipe.make_es

    def corrupted_multibuffer(cfg):
        buffer = make_multibuffer(cfg)
        sample = buffer.sample

        def corrupted_sample(*args, **kwargs):
            batch = sample(*args, **kwargs)
            if where == "td3_batch" and active():
                batch["next", "reward"][0] = float("nan")
            return batch

        buffer.sample = corrupted_sample
        return buffer

    def corrupted_es(cfg, actor):
        es = make_es(cfg, actor)
        tell = es.tell

        def corrupted_tell(population, returns):
            if where == "es_return" and active():
                returns = torch.as_tensor(returns).clone()
                returns[0] = float("nan")
            out = tell(population, returns)
            if where == "es_mean" and active():
                with torch.no_grad():
                    es.mean[0] = float("nan")
            return out

        es.tell = corrupted_tell
        return es

    recipe.make_multibuffer, recipe.make_es = corrupted_multibuffer, corrupted_es
    sys.argv = [str(RECIPE), *overrides]
    recipe.main()


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2:])
