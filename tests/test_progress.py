"""difstar._progress: the step bar and the parameter that moved most."""

import numpy as np

from difstar._progress import moved_most, step_bar


def test_moved_most_names_the_leaf_with_the_largest_change():
    before = {"a": np.zeros(3), "b": {"c": 1.0}}
    after = {"a": np.array([0.0, -0.3, 0.1]), "b": {"c": 1.2}}
    name, change = moved_most(before, after)
    assert name == "a" and np.isclose(change, 0.3)
    assert moved_most({"x": 1.0}, {"x": 1.0}) == ("", 0.0)
    assert moved_most({}, {}) == ("", 0.0)


def test_step_bar_is_silent_without_a_label_and_ticks_with_one(capsys):
    with step_bar(None, 3) as tick:
        assert tick is None
    assert capsys.readouterr().err == ""
    with step_bar("solve", 3) as tick:
        tick("χ² 12.5")
        tick()
    err = capsys.readouterr().err
    assert "solve" in err and "1/3" in err and "2/3" in err and "χ² 12.5" in err
