"""The pupils' former module, kept so that the modules importing from it still work: the
pupils live in :mod:`difstar.pupils` (one module per family); new code imports from
there."""

from .pupils._base import AbstractPupil as AbstractPupil
from .pupils._base import Transformed as Transformed
from .pupils._base import _check_build_count as _check_build_count
from .pupils._distorted import distorted as distorted
from .pupils._mask import Mask as Mask
from .pupils._obstructed import Obstructed as Obstructed
from .pupils._obstructed import Spiders as Spiders
from .pupils._obstructed import Struts as Struts
from .pupils._polygons import Circle as Circle
from .pupils._polygons import Polygon as Polygon
from .pupils._polygons import RegularPolygon as RegularPolygon
from .pupils._polygons import regular_polygon_vertices as regular_polygon_vertices
from .pupils._raster import _safe_norm as _safe_norm
from .pupils._raster import convex_polygon_coverage as convex_polygon_coverage
from .pupils._raster import disc_coverage as disc_coverage
from .pupils._raster import edge_coverage as edge_coverage
from .pupils._raster import halfplane_coverage as halfplane_coverage
from .pupils._raster import outline_coverage as outline_coverage
from .pupils._raster import polygon_coverage as polygon_coverage
from .pupils._raster import tiled_outline_coverage as tiled_outline_coverage
from .pupils._union import Union as Union
from .pupils._union import hex_segment_centres as hex_segment_centres
from .pupils._union import hex_segments as hex_segments
