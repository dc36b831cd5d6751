"""Algorithm 1's ES step: g generations of OpenAI-ES whose offspring trajectories feed the buffers."""
from __future__ import annotations

from collections.abc import Callable

import torch

from torchrl_esrl.errors import check_finite


def es_phase(
    es,
    es_collector,
    buffer,
    threshold,
    generations: int,
    shared_buffer: bool = False,
    on_generation: Callable[[int], None] | None = None,
) -> list[torch.Tensor]:
    """Run ``generations`` generations (ask, evaluate one episode each, route, tell).

    Each offspring's trajectory goes to ``good`` when its return reaches the threshold, else to
    ``bad`` (offspring by offspring, as Algorithm 1). ``shared_buffer`` is the ERL-style ablation:
    every transition to one buffer (``noisy``), no routing. Returns each generation's returns.
    """
    returns = []
    for index in range(generations):
        population = es.ask()
        generation = es_collector.evaluate(population)
        good = threshold.route(generation.returns)
        if shared_buffer:
            buffer.extend(generation.transitions, "noisy")
        else:
            buffer.extend(generation.transitions[generation.member_mask(good)], "good")
            buffer.extend(generation.transitions[generation.member_mask(~good)], "bad")
        es.tell(generation.returns)  # raises on a non-finite return
        check_finite("ES mean", es.mean)
        returns.append(generation.returns)
        if on_generation is not None:
            on_generation(index)
    return returns
