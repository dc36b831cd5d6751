"""Runs a real recipe that asks itself to stop (SIGTERM, as a scheduler would) during its n-th TD3
gradient step, for the stop-then-resume tests:

    python tests/inject_stop.py <n> <recipe>.py <hydra overrides...>
"""
import os
import signal
import sys
from pathlib import Path

from torchrl_esrl.objectives.td3 import TD3
from torchrl_esrl.run.algorithm_info import load_recipe

RECIPES = Path(__file__).resolve().parents[1] / "recipes"


def main(n: int, script: str, overrides: list[str]) -> None:
    calls = {"steps": 0}
    gradient_step = TD3.gradient_step

    def counted(self, *args, **kwargs):
        calls["steps"] += 1
        if calls["steps"] == n:
            os.kill(os.getpid(), signal.SIGTERM)  # handled between two bytecodes: within this step
        return gradient_step(self, *args, **kwargs)

    TD3.gradient_step = counted
    recipe = load_recipe(RECIPES / script)
    sys.argv = [str(RECIPES / script), *overrides]
    recipe.main()


if __name__ == "__main__":
    main(int(sys.argv[1]), sys.argv[2], sys.argv[3:])
