"""Asynchronous ES-TD3Buffers (``es.schedule=async``; the Hogwild!-style platform suggested in the paper's Discussion, in the
spirit of AES-RL, Lee et al. 2020).

Algorithm 1 alternates: M TD3 frames, then g ES generations. Here the g generations of an
iteration run in a background thread *while* the main thread does the TD3 phase. The ES thread
works from the mean as it stood at the start of the iteration (it owns the ES state until the
iteration ends), and the overwrite rule is applied at the iteration boundary, after both halves
have finished, exactly as in the sequential loop. Frames per iteration are unchanged, so the two
modes compare at equal frames (``benchmarks/async_vs_sequential.py``).

Threads, not processes: the expensive parts of both halves (MuJoCo stepping, torch kernels)
release the GIL, and a thread shares the buffers without copying transitions between processes.
The MultiBuffer and the Threshold are shared by both threads, so both are wrapped by
:class:`Guarded`: every method call on either runs under one lock (a TD3 batch is never sampled
from a half-written buffer, and routing reads a consistent best return). TorchRL buffers have a
lock of their own per buffer, but the MultiBuffer reads three of them and the Threshold has none.
"""
from __future__ import annotations

import functools
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor

import torch



class Guarded:
    """Proxy that runs every method of ``target`` under ``lock`` (attributes are read as they are)."""

    def __init__(self, target, lock: threading.RLock):
        object.__setattr__(self, "_target", target)
        object.__setattr__(self, "_lock", lock)

    def __getattr__(self, name):
        attribute = getattr(self._target, name)
        if not callable(attribute):
            return attribute
        lock = self._lock

        @functools.wraps(attribute)
        def locked(*args, **kwargs):
            with lock:
                return attribute(*args, **kwargs)

        return locked

    def __setattr__(self, name, value):
        with self._lock:
            setattr(self._target, name, value)

    def __len__(self) -> int:
        with self._lock:
            return len(self._target)

    def __getitem__(self, key):
        return self._target[key]

    def __repr__(self) -> str:
        return f"Guarded({self._target!r})"


class BackgroundES:
    """Runs an iteration's ES generations (``work``, a call of :func:`~torchrl_esrl.algorithm.es_phase.es_phase`)
    in a background thread. :class:`~torchrl_esrl.algorithm.es_phase.ESPhase` builds it::

        buffer, threshold = BackgroundES.guard(buffer, threshold)  # both halves use these from then on
        background = BackgroundES(functools.partial(es_phase, es, es_collector, buffer, threshold, g))
        background.start()                          # ES generations from the current mean ...
        td3_phase(..., buffer, on_episode=threshold.observe)   # ... while TD3 trains
        generation_returns = background.join()      # iteration boundary: evaluate, overwrite rule

    Between ``start`` and ``join`` the ES object, the ES collector and the phase's population step
    (which runs in the thread) belong to it.
    """

    def __init__(self, work: Callable[[], list[torch.Tensor]]):
        self.work = work
        self.executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="es-generations")
        self.future: Future | None = None

    @staticmethod
    def guard(buffer, threshold) -> tuple[Guarded, Guarded]:
        """``buffer`` and ``threshold`` behind one lock, shared by the ES thread and the TD3 loop."""
        lock = threading.RLock()
        return Guarded(buffer, lock), Guarded(threshold, lock)

    def start(self) -> None:
        if self.future is not None:
            raise RuntimeError("BackgroundES.start: the previous iteration's generations were not joined")
        self.future = self.executor.submit(self.work)

    def join(self) -> list[torch.Tensor]:
        """Wait for the generations (re-raising their exception, if any) and return their returns."""
        if self.future is None:
            raise RuntimeError("BackgroundES.join: nothing was started")
        future, self.future = self.future, None
        return future.result()

    def close(self) -> None:
        self.executor.shutdown(wait=True)
