"""Aperture design studies: the measures of curved-blade irises over a sweep of designs
(``difstar design`` uses them). The design problem itself (:func:`difstar.design`, its
measures such as :func:`difstar.spike_energy`) is in the top-level package."""

from ._design_study import curvature_grid as curvature_grid
from ._design_study import iris_study as iris_study
from ._design_study import measures_fn as measures_fn
from ._design_study import study_objective as study_objective
from ._design_study import study_setup as study_setup
from ._design_study import study_start as study_start
from ._design_study import sweep_designs as sweep_designs
from ._design_study import table_markdown as table_markdown

__all__ = ["curvature_grid", "iris_study", "measures_fn", "study_objective", "study_setup",
           "study_start", "sweep_designs", "table_markdown"]
