"""Networks: the paper's actor and critics, the flat-parameter bridge ES searches over, and the
batched population actor."""
from torchrl_esrl.modules.networks import flat_parameters, load_flat_parameters, make_actor, make_critic
from torchrl_esrl.modules.population import PopulationActor

__all__ = ["PopulationActor", "flat_parameters", "load_flat_parameters", "make_actor", "make_critic"]
