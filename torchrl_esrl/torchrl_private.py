"""Every use of a TorchRL (or tensordict) private attribute in this project, fenced in one place.

TorchRL's public API does not cover a few things this project needs (the reasons are given per
function). Each access goes through a function here, so a TorchRL upgrade that renames one breaks
this module only, and ``tests/test_torchrl_private.py`` fails loudly naming what changed.
Nothing outside this module may touch a name starting with ``_`` on a TorchRL object.
"""
from __future__ import annotations

# ------------------------------------------------------------------------ data (replay buffers)


# ---------------------------------------------------------------------- objectives (TD3 loss)


# ------------------------------------------------------------------ collectors (TD3 env state)
