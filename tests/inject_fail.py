"""Runs a real recipe whose final stage fails, for the finish tests:

    python tests/inject_fail.py <where> <recipe>.py <hydra overrides...>

``where``: ``figure`` (drawing the learning curve raises, as figure code that assumes a column the
run does not log did) or ``summary_write`` (writing ``summary.json`` finds the disk full).
"""
import errno
import os
import sys
from pathlib import Path

import torchrl_esrl.run.plot as plot
from torchrl_esrl.run.algorithm_info import load_recipe

RECIPES = Path(__file__).resolve().parents[1] / "recipes"
WHERE = ("figure", "summary_write")


def main(where: str, script: str, overrides: list[str]) -> None:
    if where not in WHERE:
        raise SystemExit(f"usage: inject_fail.py <{'|'.join(WHERE)}> <recipe>.py <overrides>, got {where!r}")
    if where == "figure":

        def draw(ax, run, returned=plot.RETURNED_POLICY):
            raise KeyError("es_eval_return")

        plot.draw_es_vs_td3 = draw
    else:
        write_text = Path.write_text

        def full_disk(self, data, *args, **kwargs):
            if self.name.startswith("summary.json"):
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self))
            return write_text(self, data, *args, **kwargs)

        Path.write_text = full_disk
    recipe = load_recipe(RECIPES / script)
    sys.argv = [str(RECIPES / script), *overrides]
    recipe.main()


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], sys.argv[3:])
