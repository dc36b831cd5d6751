"""Evolution strategies over an actor's flat parameters: OpenAI-ES (ES-TD3Buffers' ES half) and
the diagonal CEM of the CEM-RL baseline."""
from torchrl_esrl.es.openes import OpenES, centered_ranks

__all__ = ["OpenES", "centered_ranks"]
