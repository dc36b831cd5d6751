"""The learners of Algorithm 1's TD3 phase over TorchRL's losses: TD3 (``TD3Loss``, the paper's),
DDPG (``DDPGLoss``) and SAC (``SACLoss``), and :func:`make_learner`, which builds the config's."""
from torchrl_esrl.objectives.td3 import TD3
from torchrl_esrl.objectives.learner import Learner
from torchrl_esrl.objectives.ddpg import DDPG
from torchrl_esrl.objectives.sac import SAC
from torchrl_esrl.objectives.learners import make_learner

__all__ = ["DDPG", "Learner", "SAC", "TD3", "make_learner"]
