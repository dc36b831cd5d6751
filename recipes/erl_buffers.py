"""ERL with ES-TD3Buffers' return-routed MultiBuffer (in neither paper).

    python recipes/erl_buffers.py env=halfcheetah experiment=quick

recipes/erl.py with its one shared buffer replaced by the good, bad and noisy buffers of ES-TD3Buffers
(Section 3.1): each generation, the population's episodes go to *good* when their return reaches the
threshold (``data/threshold.py``, ``0.9 x best``), else to *bad*, episode by episode in population order;
the learner's episodes go to *noisy*, as TD3's own transitions do in ES-TD3Buffers, and their returns raise
the best. The learner trains on batches drawn at ``buffer.ratio`` once every buffer holds K
(``buffer.min_size``). Everything else is recipes/erl.py, whose ``train`` this is, with
``buffer.mode=multi`` (conf/erl_buffers.yaml); ``buffer.mode=shared`` runs ERL itself. Where the routing is
this project's choice, docs/deviations.md says so.
"""
from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from torchrl_esrl.run.algorithm_info import load_recipe
from torchrl_esrl.run.lifecycle import Run, recipe_main

erl = load_recipe(Path(__file__).with_name("erl.py"))
ALGORITHMS = erl.ALGORITHMS[3:]  # buffer.mode=multi, by learner
algorithm, holdings = erl.algorithm, erl.holdings  # the variant a config runs, what it builds: as ERL's
# experiment=tiny as ERL's, and a K that the good and bad buffers reach within its first generations.
TINY_OVERRIDES = (*erl.TINY_OVERRIDES, "buffer.min_size=64")


def train(cfg: DictConfig, run: Run) -> dict:
    """recipes/erl.py's (a function of this file, so that Hydra names the run's log after it)."""
    return erl.train(cfg, run)


main = recipe_main(train, config_name="erl_buffers", algorithm=algorithm, holdings=holdings, sections=erl.SECTIONS)

if __name__ == "__main__":
    main()
