"""A job's share of the cores and the run's thread count (torchrl_esrl/threads.py); the launcher cases run real
sweeps in tests/test_launchers.py, the resumed runs are in tests/test_lifecycle.py."""
import os

import pytest
import torch

from torchrl_esrl.threads import JOBS_VARIABLE, RunThreads, concurrent_jobs, job_cores, process_cores, torch_threads


@pytest.mark.parametrize("cores", [1, 2, 8, 64])
def test_a_single_job_takes_all_of_its_cores(monkeypatch, cores):
    monkeypatch.delenv(JOBS_VARIABLE, raising=False)
    assert concurrent_jobs(cores) == 1 and job_cores(cores) == cores  # no cap: 64 cores, 64 threads


@pytest.mark.parametrize("cores, share", [(1, 1), (2, 1), (8, 4), (64, 32)])
def test_two_jobs_side_by_side_take_half_each_and_never_zero(monkeypatch, cores, share):
    monkeypatch.setenv(JOBS_VARIABLE, "2")
    assert job_cores(cores) == share


def test_more_jobs_than_cores_get_one_core_each(monkeypatch):
    monkeypatch.setenv(JOBS_VARIABLE, "64")
    assert job_cores(8) == 1


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="CPU affinity is Linux's")
def test_the_default_is_the_process_affinity_not_the_machines_count(monkeypatch):
    monkeypatch.delenv(JOBS_VARIABLE, raising=False)
    allowed = os.sched_getaffinity(0)
    one_core = {min(allowed)}
    try:
        os.sched_setaffinity(0, one_core)  # as `taskset -c 0` or a one-core Slurm allocation
        assert process_cores() == 1 and job_cores() == 1
    finally:
        os.sched_setaffinity(0, allowed)
    assert process_cores() == len(allowed) and job_cores() == len(allowed)


def test_torch_threads_restores_the_callers_count():
    before = torch.get_num_threads()
    with torch_threads(1):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before


@pytest.fixture
def restores_torch_threads():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def test_a_checkpoint_written_inside_a_phase_resumes_to_the_runs_count_not_the_phases(restores_torch_threads):
    """A stop between two gradient steps saves the run's count; the resumed process, started under
    another count, computes what follows the phase under the uninterrupted run's count."""
    torch.set_num_threads(3)
    uninterrupted = RunThreads()
    with torch_threads(1):  # the phase, stopped here: the checkpoint is written
        state = uninterrupted.state_dict()
    assert state == {"torch": 3} and torch.get_num_threads() == 3
    torch.set_num_threads(2)  # a new process, another default count
    resumed = RunThreads()
    resumed.load_state_dict(state)
    assert torch.get_num_threads() == 3
    with torch_threads(1):  # the rest of the interrupted phase
        pass
    assert torch.get_num_threads() == 3 and resumed.state_dict() == state
