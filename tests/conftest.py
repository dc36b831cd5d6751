import os

# Set before torch is imported: idle OpenMP threads otherwise spin and slow MuJoCo (docs/performance.md).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# Before anything imports Ray (tests/test_ray_backend.py): loopback-only node addresses, no usage
# reporting. Ray reads these at import; set later, its nodes advertise the host address and hang.
os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
os.environ["RAY_USAGE_STATS_ENABLED"] = "0"

import pytest  # noqa: E402
import torch  # noqa: E402

torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
