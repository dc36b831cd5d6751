"""Asynchronous ES-TD3Buffers (``mode=async``; the Hogwild!-style platform suggested in the paper's Discussion, in the
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
from concurrent.futures import Future, ThreadPoolExecutor

import torch

from torchrl_esrl.algorithm.es_phase import es_phase


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
    """Runs an iteration's ES generations in a background thread.

    Build it with :meth:`wrap`, which also returns the guarded buffer and threshold that *both*
    halves must use from then on::

        background_es, buffer, threshold = BackgroundES.wrap(es, es_collector, buffer, threshold, g)
        background_es.start()                       # ES generations from the current mean ...
        td3_phase(..., buffer, on_episode=threshold.observe)   # ... while TD3 trains
        generation_returns = background_es.join()   # iteration boundary: evaluate, overwrite rule

    Between ``start`` and ``join`` the ES object and the ES collector belong to the thread.
    """

    def __init__(self, es, es_collector, buffer, threshold, generations: int, shared_buffer: bool = False):
        self.es, self.es_collector, self.buffer, self.threshold = es, es_collector, buffer, threshold
        self.generations = int(generations)
        self.shared_buffer = bool(shared_buffer)
        self.executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="es-generations")
        self.future: Future | None = None
        self.busy_seconds = 0.0

    @classmethod
    def wrap(cls, es, es_collector, buffer, threshold, generations: int, shared_buffer: bool = False):
        lock = threading.RLock()
        buffer, threshold = Guarded(buffer, lock), Guarded(threshold, lock)
        return cls(es, es_collector, buffer, threshold, generations, shared_buffer), buffer, threshold

    def start(self) -> None:
        if self.future is not None:
            raise RuntimeError("BackgroundES.start: the previous iteration's generations were not joined")
        self.future = self.executor.submit(es_phase, self.es, self.es_collector, self.buffer, self.threshold, self.generations, self.shared_buffer)

    def join(self) -> list[torch.Tensor]:
        """Wait for the generations (re-raising their exception, if any) and return their returns."""
        if self.future is None:
            raise RuntimeError("BackgroundES.join: nothing was started")
        future, self.future = self.future, None
        return future.result()

    def close(self) -> None:
        self.executor.shutdown(wait=True)
