"""benchmarks/run_floor.py: the floor's arithmetic (its doctest); its reading of a full_scale record
is tested with one in tests/test_full_scale.py."""
import doctest

from benchmarks import run_floor


def test_the_floor_adds_es_physics_on_both_cores_td3_physics_on_one_and_the_products():
    result = doctest.testmod(run_floor)
    assert result.attempted > 0 and result.failed == 0
