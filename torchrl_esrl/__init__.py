"""ES-TD3Buffers (Callaghan, Mason and Mannion, ALA 2023) as TorchRL components."""
from torchrl_esrl.algorithm.overwrite import OverwriteRule
from torchrl_esrl.algorithm.td3_phase import td3_phase
from torchrl_esrl.collectors import ESCollector, Generation
from torchrl_esrl.data import BUFFER_NAMES, MultiBuffer, Threshold, ratio_counts
from torchrl_esrl.es import OpenES, centered_ranks
from torchrl_esrl.modules import PopulationActor, flat_parameters, load_flat_parameters, make_actor, make_critic
from torchrl_esrl.objectives import TD3
from torchrl_esrl.run import schema as _schema  # noqa: F401  registers the typed config schema with Hydra

__all__ = [
    "BUFFER_NAMES",
    "ESCollector",
    "Generation",
    "MultiBuffer",
    "OpenES",
    "OverwriteRule",
    "PopulationActor",
    "TD3",
    "Threshold",
    "centered_ranks",
    "flat_parameters",
    "load_flat_parameters",
    "make_actor",
    "make_critic",
    "ratio_counts",
    "td3_phase",
]
