"""Runs a real recipe that SIGKILLs itself at a chosen moment, for the kill-then-rerun tests:

    python tests/inject_kill.py <where> <recipe>.py <hydra overrides...>

``where``: ``first_checkpoint`` (as soon as the run's first checkpoint is written, whatever the
recipe checkpoints first), ``final_evaluation`` (the first final evaluation after the last
iteration, with its checkpoint written) or ``summary_write`` (halfway through writing
``summary.json``).
"""
import importlib.util
import os
import signal
import sys
from pathlib import Path

from torchrl_esrl.run.checkpoint import RunCheckpoint
from torchrl_esrl.run.harness import RunHarness
from torchrl_esrl.run.lifecycle import Run

RECIPES = Path(__file__).resolve().parents[1] / "recipes"
WHERE = ("first_checkpoint", "final_evaluation", "summary_write")


def kill() -> None:
    os.kill(os.getpid(), signal.SIGKILL)


def main(where: str, script: str, overrides: list[str]) -> None:
    if where not in WHERE:
        raise SystemExit(f"usage: inject_kill.py <{'|'.join(WHERE)}> <recipe>.py <overrides>, got {where!r}")
    looped = {"done": False}
    iterations = Run.iterations

    def watched(self, desc):
        yield from iterations(self, desc)
        looped["done"] = True  # the last iteration's checkpoint is written

    Run.iterations = watched
    if where == "first_checkpoint":
        save = RunCheckpoint.save

        def saved_once(self):
            save(self)
            kill()

        RunCheckpoint.save = saved_once
    elif where == "final_evaluation":
        evaluate_final = RunHarness.evaluate_final

        def killed(self, vector):
            if looped["done"]:
                kill()
            return evaluate_final(self, vector)

        RunHarness.evaluate_final = killed
    else:
        write_text = Path.write_text

        def half_written(self, data, *args, **kwargs):
            if self.name.startswith("summary.json"):
                write_text(self, data[: len(data) // 2], *args, **kwargs)
                kill()
            return write_text(self, data, *args, **kwargs)

        Path.write_text = half_written
    path = RECIPES / script
    spec = importlib.util.spec_from_file_location(path.stem, path)
    recipe = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(recipe)
    sys.argv = [str(path), *overrides]
    recipe.main()


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], sys.argv[3:])
