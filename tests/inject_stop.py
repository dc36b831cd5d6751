"""Runs a real recipe that asks itself to stop (SIGTERM, as a scheduler would) at a chosen moment,
for the stop-then-resume tests:

    python tests/inject_stop.py <where>@<n> <recipe>.py <hydra overrides...>

``where``: ``gradient_step`` (during its n-th TD3 gradient step) or ``stop_point`` (as its n-th
stop point is reached, whatever the recipe's stop points are: a TD3 batch, a generation, an
iteration's end).
"""
import os
import signal
import sys
from pathlib import Path

from torchrl_esrl.objectives.td3 import TD3
from torchrl_esrl.run.algorithm_info import load_recipe
from torchrl_esrl.run.stop import StopOnSignal

RECIPES = Path(__file__).resolve().parents[1] / "recipes"
WHERE = {"gradient_step": (TD3, "gradient_step"), "stop_point": (StopOnSignal, "check")}


def main(at: str, script: str, overrides: list[str]) -> None:
    where, _, n = at.partition("@")
    if where not in WHERE or not n.isdigit():
        raise SystemExit(f"usage: inject_stop.py <{'|'.join(WHERE)}>@<n> <recipe>.py <overrides>, got {at!r}")
    owner, name = WHERE[where]
    calls = {"count": 0}
    method = getattr(owner, name)

    def counted(self, *args, **kwargs):
        calls["count"] += 1
        if calls["count"] == int(n):
            os.kill(os.getpid(), signal.SIGTERM)  # handled between two bytecodes: within this call
        return method(self, *args, **kwargs)

    setattr(owner, name, counted)
    recipe = load_recipe(RECIPES / script)
    sys.argv = [str(RECIPES / script), *overrides]
    recipe.main()


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], sys.argv[3:])
