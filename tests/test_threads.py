"""A job's share of the cores (torchrl_esrl/threads.py); the launcher cases run real sweeps in tests/test_launchers.py."""
import torch

from torchrl_esrl.threads import JOBS_VARIABLE, concurrent_jobs, job_cores, process_cores, torch_threads


def test_a_single_process_takes_all_of_its_cores(monkeypatch):
    monkeypatch.delenv(JOBS_VARIABLE, raising=False)
    assert concurrent_jobs(process_cores()) == 1 and job_cores() == process_cores()


def test_jobs_started_side_by_side_share_the_cores(monkeypatch):
    monkeypatch.setenv(JOBS_VARIABLE, "2")
    assert job_cores() == max(1, process_cores() // 2)
    monkeypatch.setenv(JOBS_VARIABLE, str(4 * process_cores()))  # more jobs than cores: one each, never zero
    assert job_cores() == 1


def test_torch_threads_restores_the_callers_count():
    before = torch.get_num_threads()
    with torch_threads(1):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before
