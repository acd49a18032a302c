"""The curved iris's former module, kept so that the modules importing from it still
work: :class:`CurvedIris` lives in :mod:`difstar.pupils` (``pupils/_curved.py``)."""

from .pupils._curved import CurvedIris as CurvedIris
from .pupils._curved import curved_iris_from_area as curved_iris_from_area
from .pupils._curved import segment_area as segment_area
from .pupils._raster import outline_coverage as outline_coverage
