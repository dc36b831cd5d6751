"""Collectors: the ES collector (one episode per offspring, paper Algorithm 2) with its population
backends (one registry, :mod:`~torchrl_esrl.collectors.backends`), and the TD3 side's collector."""
from torchrl_esrl.collectors.es_collector import ESCollector
from torchrl_esrl.collectors.generation import Generation

__all__ = ["ESCollector", "Generation"]
