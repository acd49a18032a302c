"""A fit's procedure as types (difstar.fitting.Solve, Hop, Repeat): each is the dict a
manifest writes, both ways, and a typed stage that cannot be right is refused by the same
checks, before any fitting, as its dict. (That a typed procedure fits as its dict does:
tests/test_fitting.py, the hop test.)"""

import numpy as np
import pytest

from difstar.fitting import (
    FitData,
    FitInputError,
    Hop,
    ImageModel,
    Light,
    Param,
    Repeat,
    Restart,
    Solve,
    fit,
    obstructed_circle_pupil,
)
from difstar.fitting._stage_types import parse_stage, stage_dicts

STAGES = [
    Solve(),
    Solve(free=["x0", "y0", "flux"], half=8, max_steps=20),
    Solve(free="all", fix=["rotation"], rtol=1e-5, set={"z4": 0.0}),
    Solve(free=["rotation"], annulus=(4.0, 12.0), spikes={"r_min": 4.0, "profiles": False},
          noise_from_residuals={"floor": 0.03}, reject={"above": 20.0},
          scan={"name": "rotation", "half_range": 5.0, "step": 0.5}),
    Hop(name="rotation", offsets=[-0.5, 0.5]),
    Hop(flip=["z6", ["z4", "z11"]], stages=1),
    Hop(set={"z4": 0.0}, stages=3),
    Repeat(until={"rotation": 0.002}, max_rounds=8),
    Restart("toe", (0.5,)),
]


@pytest.mark.parametrize("stage", STAGES, ids=lambda s: type(s).__name__)
def test_a_typed_stage_is_the_dict_a_manifest_writes(stage):
    (d,) = stage_dicts([stage])
    assert isinstance(d, dict)
    assert parse_stage(d) == stage
    assert stage_dicts([parse_stage(d)]) == [d]


def test_dicts_parse_with_the_defaults_filled_in():
    assert parse_stage({"free": "all", "half": None}) == Solve()
    assert parse_stage({"free": ["flux"]}) == Solve(free=("flux",))
    assert parse_stage({"hop": {"name": "rotation", "offsets": [1]}}) == Hop(
        name="rotation", offsets=(1.0,), stages=2)
    assert parse_stage({"repeat": {"until": {"flux": 0.1}}}) == Repeat(
        until={"flux": 0.1}, stages=2, max_rounds=6)
    assert Solve(free=["a", "b"]).free == ("a", "b") and Solve(fix="a").fix == ("a",)


@pytest.fixture(scope="module")
def small():
    """A 16² star and a model with a free flux and rotation: enough for the checks that
    run before any fitting."""
    y, x = np.mgrid[-8:8, -8:8]
    img = 100.0 * np.exp(-(x**2 + y**2) / 4.0) + 1.0
    data = FitData.from_array(img, sigma=1.0)
    model = ImageModel(obstructed_circle_pupil(0.425),
                       {"flux": Param(100.0, True), "rotation": Param(0.0, True, (-30, 30)),
                        "pixel_scale": Param(0.06)},
                       light=Light.monochromatic(1e-6), pad=4, accuracy=3e-2)
    return model, data


@pytest.mark.parametrize("bad, match", [
    (Hop(name="rotation"), "hop: needs one of"),  # no offsets
    (Hop(name="rotaton", offsets=[1.0]), "hop: needs one of"),
    (Hop(name="rotation", offsets=[1.0], stages=2), "hop: needs one of"),  # one stage before
    (Repeat(until={}), "repeat needs 'until'"),
    (Repeat(until={"flux": 0.1}, max_rounds=0), "repeat needs 'until'"),
    (Solve(free=["flux"], half=-1), "half"),
    (Solve(free=["flux"], spikes={"r_mn": 3}), "unknown options"),
    # a RAW fit's σ from the prediction
    (Solve(free=["flux"], sigma="prediction"), "unknown keys \\['sigma'\\]"),
])
def test_a_typed_stage_that_cannot_be_right_is_refused_as_its_dict_is(small, bad, match):
    model, data = small
    first = Solve(free=["flux"], max_steps=1)
    for stages in ([first, bad], [first.as_dict(), bad.as_dict()]):
        with pytest.raises(FitInputError, match=match):
            fit(model, data, stages=stages)


def test_an_image_fit_refuses_a_raw_fits_restart(small):
    """(A typed Restart is outside fit's type hint: its dict form is what could reach it.)"""
    model, data = small
    with pytest.raises(FitInputError, match="unknown keys \\['restart'\\]"):
        fit(model, data, stages=[Solve(free=["flux"], max_steps=1), Restart().as_dict()])
