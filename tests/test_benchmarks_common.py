"""benchmarks/common: what a benchmark record says of the machine."""
import re
from pathlib import Path

import pytest

from benchmarks.common import CPU_FLAGS, cpu_model, machine


@pytest.mark.skipif(not Path("/proc/cpuinfo").exists(), reason="the processor is read from Linux's /proc/cpuinfo")
def test_the_record_names_the_processor_and_its_matrix_instruction_sets():
    text = Path("/proc/cpuinfo").read_text()
    model = cpu_model()
    assert model["model_name"] == re.search(r"^model name\s*:\s*(.*)$", text, re.M).group(1).strip()
    assert model["model"] == re.search(r"^model\s*:\s*(\d+)$", text, re.M).group(1)
    flags = set(re.search(r"^flags\s*:\s*(.*)$", text, re.M).group(1).split())
    assert model["flags"] == [flag for flag in CPU_FLAGS if flag in flags]
    assert machine()["cpu"] == model
