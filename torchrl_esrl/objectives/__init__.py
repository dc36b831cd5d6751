"""The TD3 learner over TorchRL's ``TD3Loss`` (paper, Algorithm 1 "perform TD3 iterations")."""
from torchrl_esrl.objectives.td3 import TD3

__all__ = ["TD3"]
