"""The recovery study's progress (difstar._fit_recovery)."""

from difstar._fit_recovery import fits_left


def test_fits_left_counts_the_fits_still_to_run_at_the_mean_after_the_first():
    """After each fit of a study the line ends with the time still to come: the fits
    left times the mean time of the fits after the first (the first compiles), the
    first's own time while it is the only one, nothing after the last."""
    rows = [{"seconds": 30.0}]
    assert fits_left(rows, 3) == ", about 60 s left"
    rows += [{"seconds": 10.0}, {"seconds": 12.0}]
    assert fits_left(rows, 5) == ", about 22 s left"
    assert fits_left(rows, 3) == ""
