"""Evolution strategies over an actor's flat parameters, one ask/tell interface
(:mod:`~torchrl_esrl.es.strategy`): OpenAI-ES (ES-TD3Buffers' ES half), the diagonal CEM of
the CEM-RL baseline and ERL's genetic algorithm."""
from torchrl_esrl.es.ga import GeneticAlgorithm
from torchrl_esrl.es.openes import OpenES, centered_ranks
from torchrl_esrl.es.strategy import EvolutionStrategy

__all__ = ["EvolutionStrategy", "GeneticAlgorithm", "OpenES", "centered_ranks"]
