"""metrics.csv: columns come from the first row (or the file a resumed run continues); a row with
other keys raises instead of being cut to the known columns."""
import pytest

from torchrl_esrl.run.metrics import MetricsLog, read_metrics


def test_columns_are_the_first_rows_keys_and_other_keys_raise(tmp_path):
    log = MetricsLog(tmp_path, backend="", experiment_name="test")
    log.log({"iteration": 0, "eval_return": 1.5, "overwritten": True})
    with pytest.raises(KeyError, match="unknown \\['typo'\\]"):
        log.log({"iteration": 1, "eval_return": 2.0, "overwritten": False, "typo": 3})
    with pytest.raises(KeyError, match="missing \\['overwritten'\\]"):
        log.log({"iteration": 1, "eval_return": 2.0})
    assert read_metrics(tmp_path / "metrics.csv") == [{"iteration": 0, "eval_return": 1.5, "overwritten": True}]


def test_a_resumed_log_continues_the_files_columns(tmp_path):
    MetricsLog(tmp_path, backend="", experiment_name="test").log({"iteration": 0, "eval_return": 1.0})
    resumed = MetricsLog(tmp_path, backend="", experiment_name="test")
    assert resumed.columns() == ("iteration", "eval_return")
    resumed.log({"iteration": 1, "eval_return": 2.0})
    with pytest.raises(KeyError):
        resumed.log({"eval_return": 3.0, "iteration": 2})  # same keys, another order
    assert [r["iteration"] for r in read_metrics(tmp_path / "metrics.csv")] == [0, 1]


@pytest.mark.parametrize(
    "cut, words",
    [
        (lambda data: data[:-7], "line 3 is cut short (no line end)"),  # a kill or a full disk mid-row
        (lambda data: data[: data.rindex(b",")] + b"\r\n", "line 3 has 2 fields, the header 3"),
        (lambda data: data[:40] + b"\0" * 8 + data[48:], "line 2 holds a NUL byte"),  # a block lost in a crash
    ],
    ids=["cut", "fields", "nul"],
)
def test_a_damaged_file_is_one_error_naming_it_and_the_line(tmp_path, cut, words):
    log = MetricsLog(tmp_path, backend="", experiment_name="test")
    for iteration in range(2):
        log.log({"iteration": iteration, "eval_return": 1.5 + iteration, "overwritten": True})
    path = tmp_path / "metrics.csv"
    path.write_bytes(cut(path.read_bytes()))
    with pytest.raises(ValueError) as error:
        read_metrics(path)
    assert str(error.value) == f"{path} is damaged: {words}"
