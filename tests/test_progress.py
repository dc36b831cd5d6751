"""torchrl_esrl/run/progress.py: the iteration's evaluations a checkpoint holds are given back, in
order, once each, to the process that restores it; a new iteration starts with none."""
from torchrl_esrl.run.progress import RunProgress


def test_recorded_evaluations_are_given_back_once_in_order_after_a_restore():
    progress = RunProgress()
    assert progress.recorded_evaluation() is None  # nothing recorded: evaluate
    progress.record_evaluation(12.5)
    progress.record_evaluation(-3.0)
    assert progress.recorded_evaluation() is None  # this process played them itself
    restored = RunProgress()
    restored.load_state_dict(progress.state_dict())
    assert [restored.recorded_evaluation(), restored.recorded_evaluation(), restored.recorded_evaluation()] == [12.5, -3.0, None]
    restored.finish_iteration()
    assert restored.evaluations == [] and restored.recorded_evaluation() is None


def test_a_checkpoint_from_before_evaluations_were_kept_restores_with_none():
    state = RunProgress().state_dict()
    del state["evaluations"]
    restored = RunProgress()
    restored.load_state_dict(state)
    assert restored.evaluations == [] and restored.recorded_evaluation() is None
