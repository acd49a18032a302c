"""Pupils: the aperture families (also in the top-level package) and the rasterisation
of an outline into pupil-plane coverage that they are drawn with.

Every shape gives, for a grid of square sample cells, the fraction of each cell that lies
inside the shape (lengths in metres in the exit-pupil plane). Its modules, in the order
they build on one another: ``_raster`` (coverage of half-planes, edges, outlines, discs),
``_base`` (:class:`AbstractPupil`, :class:`Transformed`, the checks made when a pupil is
built), ``_polygons`` (:class:`Polygon`, :class:`RegularPolygon`, :class:`Circle`),
``_curved`` (:class:`CurvedIris`), ``_obstructed`` (:class:`Spiders`, :class:`Struts`,
:class:`Obstructed`), ``_union`` (:class:`Union`, hexagonal segments), ``_mask``
(:class:`Mask`) and ``_distorted`` (:func:`distorted`, a pupil under a linear map).
"""

from ._base import AbstractPupil as AbstractPupil
from ._base import Transformed as Transformed
from ._curved import CurvedIris as CurvedIris
from ._curved import curved_iris_from_area as curved_iris_from_area
from ._mask import Mask as Mask
from ._obstructed import Obstructed as Obstructed
from ._obstructed import Spiders as Spiders
from ._obstructed import Struts as Struts
from ._polygons import Circle as Circle
from ._polygons import Polygon as Polygon
from ._polygons import RegularPolygon as RegularPolygon
from ._polygons import regular_polygon_vertices as regular_polygon_vertices
from ._raster import outline_coverage as outline_coverage
from ._raster import tiled_outline_coverage as tiled_outline_coverage
from ._union import Union as Union
from ._union import hex_segment_centres as hex_segment_centres
from ._union import hex_segments as hex_segments

__all__ = [
    "AbstractPupil",
    "Circle",
    "CurvedIris",
    "Mask",
    "Obstructed",
    "Polygon",
    "RegularPolygon",
    "Spiders",
    "Struts",
    "Transformed",
    "Union",
    "curved_iris_from_area",
    "hex_segment_centres",
    "hex_segments",
    "outline_coverage",
    "regular_polygon_vertices",
    "tiled_outline_coverage",
]
