"""Numerical faults (issue #5): NaN or inf in a loss, the ES mean or an episode return stops the
run with a one-line message; nothing is checkpointed after it.

``TD3.update`` and ``OpenES.gradient`` raise :class:`FloatingPointError` themselves;
:func:`check_finite` covers the ES mean and the returns the recipe reads. For tests, the
environment variable ``ESRL_INJECT_NAN=<where>@<iteration>`` corrupts the real run on purpose:

- ``td3_batch``: the reward of the first item of a TD3 batch (the critic loss turns NaN);
- ``es_return``: the first offspring return handed to ``OpenES.tell``;
- ``es_mean``: the ES mean right after ``OpenES.tell``.
"""
from __future__ import annotations

import os

import torch

INJECT_ENV_VAR = "ESRL_INJECT_NAN"
INJECTION_POINTS = ("td3_batch", "es_return", "es_mean")


def inject_faults_from_env(progress, es, buffer, spec: str | None = None) -> None:
    """Install the NaN injection named by ``ESRL_INJECT_NAN`` (no-op when it is unset)."""
    spec = os.environ.get(INJECT_ENV_VAR, "") if spec is None else spec
    if not spec:
        return
    where, _, at = spec.partition("@")
    if where not in INJECTION_POINTS or not at.isdigit():
        raise ValueError(f"{INJECT_ENV_VAR}={spec!r} (allowed: <{'|'.join(INJECTION_POINTS)}>@<iteration>)")
    iteration = int(at)

    def active() -> bool:
        return progress.iteration == iteration

    if where == "td3_batch":
        sample = buffer.sample

        def corrupted_sample(*args, **kwargs):
            batch = sample(*args, **kwargs)
            if active():
                batch["next", "reward"][0] = float("nan")
            return batch

        buffer.sample = corrupted_sample
    else:
        tell = es.tell

        def corrupted_tell(returns):
            if where == "es_return" and active():
                returns = torch.as_tensor(returns).clone()
                returns[0] = float("nan")
            out = tell(returns)
            if where == "es_mean" and active():
                with torch.no_grad():
                    es.mean[0] = float("nan")
            return out

        es.tell = corrupted_tell
