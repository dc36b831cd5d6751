"""ES-TD3Buffers (Callaghan, Mason and Mannion, ALA 2023) as TorchRL components."""
from torchrl_esrl.buffers import BUFFER_NAMES, MultiBuffer, ratio_counts
from torchrl_esrl.es import OpenES, centered_ranks
from torchrl_esrl.es_collector import ESCollector, Generation
from torchrl_esrl.networks import PopulationActor, flat_parameters, load_flat_parameters, make_actor, make_critic
from torchrl_esrl.overwrite import OverwriteRule
from torchrl_esrl import schema as _schema  # noqa: F401  registers the typed config schema with Hydra
from torchrl_esrl.td3 import TD3, td3_phase
from torchrl_esrl.threshold import Threshold

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
