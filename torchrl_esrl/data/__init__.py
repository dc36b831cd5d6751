"""Replay data of ES-TD3Buffers (paper, Section 3.1): the good/bad/noisy MultiBuffer and the
threshold that routes ES trajectories into it."""
from torchrl_esrl.data.multibuffer import BUFFER_NAMES, TRANSITION_KEYS, MultiBuffer, ratio_counts
from torchrl_esrl.data.threshold import Threshold

__all__ = ["BUFFER_NAMES", "TRANSITION_KEYS", "MultiBuffer", "Threshold", "ratio_counts"]
