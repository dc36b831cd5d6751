"""Evolution strategies over an actor's flat parameters, one ask/tell interface
(:mod:`~torchrl_esrl.es.strategy`): OpenAI-ES (ES-TD3Buffers' ES half) and the diagonal CEM of
the CEM-RL baseline."""
from torchrl_esrl.es.openes import OpenES, centered_ranks
from torchrl_esrl.es.strategy import EvolutionStrategy

__all__ = ["EvolutionStrategy", "OpenES", "centered_ranks"]
