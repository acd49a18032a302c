"""Pupils: the aperture families (also in the top-level package) and the rasterisation
of a polygon's outline into pupil-plane coverage that they are drawn with."""

from ._pupil import AbstractPupil as AbstractPupil
from ._pupil import Circle as Circle
from ._pupil import Mask as Mask
from ._pupil import Obstructed as Obstructed
from ._pupil import Polygon as Polygon
from ._pupil import RegularPolygon as RegularPolygon
from ._pupil import Spiders as Spiders
from ._pupil import Struts as Struts
from ._pupil import Transformed as Transformed
from ._pupil import Union as Union
from ._pupil import hex_segment_centres as hex_segment_centres
from ._pupil import hex_segments as hex_segments
from ._pupil import outline_coverage as outline_coverage
from ._pupil import regular_polygon_vertices as regular_polygon_vertices
from ._pupil import tiled_outline_coverage as tiled_outline_coverage
from ._pupil_curved import CurvedIris as CurvedIris
from ._pupil_curved import curved_iris_from_area as curved_iris_from_area

__all__ = [
    "AbstractPupil", "Circle", "CurvedIris", "Mask", "Obstructed", "Polygon",
    "RegularPolygon", "Spiders", "Struts", "Transformed", "Union", "curved_iris_from_area",
    "hex_segment_centres", "hex_segments", "outline_coverage", "regular_polygon_vertices",
    "tiled_outline_coverage",
]
