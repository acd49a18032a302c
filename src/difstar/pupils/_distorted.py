"""A pupil under a linear map (image-plane distortion: shear and aspect):
:func:`distorted` maps each family exactly where it can, else wraps it in
:class:`Transformed`."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ._base import _concrete, _float
from ._obstructed import Obstructed, Spiders, Struts
from ._polygons import Circle, Polygon, RegularPolygon
from ._raster import _safe_norm
from ._union import Union


def distorted(pupil, matrix):
    """``pupil`` with every point p mapped to ``matrix`` @ p (a 2 × 2 linear map with a
    positive determinant, traceable): the pupil that produces the image of the
    original pupil seen through the image-plane linear map D = matrix^(−T) (Fraunhofer:
    transforming the pupil by B transforms the far field by B^(−T)), e.g. a detector or
    resampling grid with a shear or unequal x and y scales.

    Exact for polygons, unions of them and :class:`Struts` (their centre lines and
    widths are mapped; their far ends, beyond the pupil, stay square). A :class:`Circle`
    becomes the circle of the same area (an ellipse with axes differing by the map's
    anisotropy would be exact: a first-order error in that anisotropy on the circle's
    own, round, contribution to the image). :class:`Obstructed` maps its parts. Other
    pupils raise ``TypeError``.
    """
    m = _float(matrix)
    if m.shape != (2, 2):
        raise ValueError(f"distorted: matrix must be 2 × 2; got shape {m.shape}.")
    det = m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]
    c = _concrete(det)
    if c is not None and not (np.isfinite(c) and c > 0):
        raise ValueError(f"distorted: the matrix's determinant must be > 0 (no "
                         f"reflection, not singular); got {float(c)}.")
    if isinstance(pupil, Polygon):
        return Polygon(pupil.vertices @ m.T)
    if isinstance(pupil, RegularPolygon):
        return distorted(Polygon(pupil.outline_edges()[0]), m)
    if isinstance(pupil, Union):
        return Union([distorted(q, m) for q in pupil.members], check_overlap=False)
    if isinstance(pupil, Circle):
        return Circle(pupil.radius * jnp.sqrt(det), m @ pupil.centre)
    if isinstance(pupil, Obstructed):
        return Obstructed(distorted(pupil.outer, m),
                          None if pupil.obstruction is None
                          else distorted(pupil.obstruction, m),
                          None if pupil.spiders is None else distorted(pupil.spiders, m))
    if isinstance(pupil, Spiders):
        return distorted(pupil.transformed(0.0), m)
    if isinstance(pupil, Struts):
        u = jnp.stack([jnp.cos(pupil.angles), jnp.sin(pupil.angles)], axis=-1) @ m.T
        stretch = _safe_norm(u[:, 0], u[:, 1])  # |M u|: lengths along the strut
        across = det / stretch  # widths and offsets across it
        return Struts(jnp.arctan2(u[:, 1], u[:, 0]), pupil.widths * across,
                      pupil.offsets * across,
                      None if pupil.length is None else pupil.length * stretch,
                      start=pupil.start * stretch, centre=m @ pupil.centre)
    raise TypeError(f"distorted: {type(pupil).__name__} is not supported (polygons, unions, "
                    "circles, struts and obstructed pupils are).")
