import pickle

import cloudpickle
import pytest

from sb3_collapse.drqv2.schedules import StddevSchedule


def test_constant_forms():
    assert StddevSchedule(0.2)(0) == 0.2
    assert StddevSchedule(0.2)(10**7) == 0.2
    assert StddevSchedule("0.3")(123) == 0.3
    assert StddevSchedule(1)(5) == 1.0


def test_linear_matches_drqv2():
    schedule = StddevSchedule("linear(1.0,0.1,100000)")
    assert schedule(0) == pytest.approx(1.0)
    assert schedule(50_000) == pytest.approx(0.55)
    assert schedule(100_000) == pytest.approx(0.1)
    assert schedule(1_000_000) == pytest.approx(0.1)


def test_linear_accepts_spaces_and_exponents():
    assert StddevSchedule(" linear( 1.0 , 0.1 , 1e5 ) ")(100_000) == pytest.approx(0.1)


def test_step_linear():
    schedule = StddevSchedule("step_linear(1.0,0.5,100,0.1,200)")
    assert schedule(0) == pytest.approx(1.0)
    assert schedule(50) == pytest.approx(0.75)
    assert schedule(100) == pytest.approx(0.5)
    assert schedule(200) == pytest.approx(0.3)
    assert schedule(300) == pytest.approx(0.1)
    assert schedule(10_000) == pytest.approx(0.1)


def test_callable():
    schedule = StddevSchedule(lambda step: 1.0 / (1 + step))
    assert schedule(0) == 1.0
    assert schedule(3) == 0.25


@pytest.mark.parametrize(
    "spec",
    [
        "linear(1.0,0.1)",
        "linear(a,b,c)",
        "exp(1,2,3)",
        "",
        "linear(1.0,0.1,0)",
        "step_linear(1,0.5,100,0.1)",
        None,
        [1],
    ],
)
def test_malformed_raises_value_error(spec):
    with pytest.raises(ValueError, match="stddev schedule"):
        StddevSchedule(spec)


@pytest.mark.parametrize("spec", [-0.1, "-1", float("nan"), lambda step: -1.0])
def test_negative_or_nan_std_raises(spec):
    with pytest.raises(ValueError, match="standard deviation"):
        StddevSchedule(spec)


def test_pickle_round_trip():
    for spec in ["linear(1.0,0.1,100000)", 0.2]:
        restored = pickle.loads(pickle.dumps(StddevSchedule(spec)))
        assert restored(50_000) == StddevSchedule(spec)(50_000)
    restored = cloudpickle.loads(cloudpickle.dumps(StddevSchedule(lambda step: 0.5)))
    assert restored(7) == 0.5
