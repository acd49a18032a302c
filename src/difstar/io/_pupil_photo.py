"""The pupil polygon from a photograph of the lens's aperture (paper, Supplementary Fig. B.1).

``estimate_pupil_polygon(image)`` finds the aperture (the largest region on one side of
an Otsu threshold that does not touch the image border), traces its edge with
sub-pixel precision (``skimage.measure.find_contours`` at the level halfway between the
aperture's and the background's intensity, which is where a blurred straight edge lies),
and fits a polygon: with the blade count n known, n straight sides are fitted by total
least squares to the contour points between the candidate corners (away from the rounded
corners), and consecutive sides are intersected for the vertices; with n unknown, n is
inferred from the corners of a Douglas–Peucker simplification
(``skimage.measure.approximate_polygon``) whose tolerance scales with the size, cleaned
of near-straight and near-duplicate corners, and confirmed by the fit residual.

The result serves as a start value for the inverse fit and as an independent check of
the polygon that fit recovers. This module runs outside the jitted core (NumPy and
scikit-image, imported lazily).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

Real = float | int | np.integer | np.floating
_MAX_INFERRED = 24  # inferred blade counts above this are taken as noise


class PupilPhotoError(ValueError):
    """No usable aperture in the photo, or a polygon that cannot be fitted."""


@dataclasses.dataclass(frozen=True, eq=False)
class PupilPolygon:
    """A polygon fitted to a photo of the aperture.

    Attributes
    ----------
    vertices : (n, 2) float64 metres, counter-clockwise, origin at the polygon's
        centroid, x to the right and y up (image rows go down; they are flipped). The
        first vertex is the one nearest the angle ``rotation``.
    circumradius : metres, the mean distance of the vertices from the centroid.
    rotation : radians in [0, 2π/n), the angle of the first vertex of the regular n-gon
        that best matches the vertices (circular mean of θ_k − 2πk/n), the convention of
        ``difstar._pupil.RegularPolygon``.
    n_blades : number of sides.
    n_blades_inferred : True when n was inferred from the photo, False when given.
    centroid_px : (row, col) of the centroid in image pixels.
    residual_rms_px : RMS distance, in pixels, of the edge points used from their side.
    """

    vertices: np.ndarray
    circumradius: float
    rotation: float
    n_blades: int
    n_blades_inferred: bool
    centroid_px: tuple[float, float]
    residual_rms_px: float


def estimate_pupil_polygon(
    image: np.ndarray,
    *,
    n_blades: int | np.integer | None = None,
    pixel_size: Real = 1.0,
) -> PupilPolygon:
    """Fit a polygon to the aperture in a photo.

    Parameters
    ----------
    image : (h, w) float, a photo of the aperture (brighter or darker than its
        surroundings; the side that does not touch the image border is taken as the
        aperture). Any linear intensity scale.
    n_blades : number of sides (≥ 3) when known; None to infer it.
    pixel_size : metres per image pixel at the pupil (1.0 gives the result in pixels).

    Returns a ``PupilPolygon``. Raises ``PupilPhotoError`` (a ``ValueError``) when no
    aperture can be found or the polygon cannot be fitted.
    """
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2 or min(img.shape) < 8:
        raise PupilPhotoError(f"image must be 2-D (h, w) with h, w ≥ 8; got shape {img.shape}")
    if not np.all(np.isfinite(img)):
        raise PupilPhotoError("image contains NaN or infinite values")
    if n_blades is not None and (int(n_blades) != n_blades or n_blades < 3):
        raise PupilPhotoError(f"n_blades must be an integer ≥ 3 or None; got {n_blades!r}")
    if not pixel_size > 0:
        raise PupilPhotoError(f"pixel_size must be > 0 m/pixel; got {pixel_size!r}")

    contour = _aperture_contour(img)  # (k, 2) (row, col), closed, no repeated last point
    size = math.sqrt(abs(_area(contour)) / math.pi)  # equivalent radius, px

    inferred = n_blades is None
    if inferred:
        corners = _candidate_corners(contour, size, n=None)
        n = len(corners)
        if n < 3:
            raise PupilPhotoError(
                f"could not infer the blade count: the aperture outline has {n} corners "
                "(a circle or a very rounded aperture?); pass n_blades"
            )
    else:
        n = int(n_blades)
        corners = _candidate_corners(contour, size, n=n)

    verts, rms, dirs = _fit_sides(contour, corners)
    while inferred and n > 3:
        # A vertex where the fitted sides barely turn splits one side in two; a short
        # side whose two end turns together make only about one corner's turn is a
        # rounded corner seen as two. Neither is a blade: remove it and refit.
        ang = np.arctan2(dirs[:, 1], dirs[:, 0])
        turn = np.abs(np.angle(np.exp(1j * (ang - np.roll(ang, 1)))))  # at vertex i
        sides = np.hypot(*(np.roll(verts, -1, axis=0) - verts).T)
        step = 2 * np.pi / n
        pair = turn + np.roll(turn, -1)  # the two end turns of side j (vertices j, j+1)
        short = (sides < 0.6 * np.median(sides)) & (pair < 1.5 * step)
        if turn.min() < 0.35 * step:
            corners = np.delete(corners, int(np.argmin(turn)))
        elif short.any():
            j = int(np.argmin(np.where(short, sides, np.inf)))
            corners = _merge_corners(contour, corners, j)
        else:
            break
        n = len(corners)
        verts, rms, dirs = _fit_sides(contour, corners)
    if inferred and n > _MAX_INFERRED:
        raise PupilPhotoError(
            f"no polygonal aperture found: the outline has {n} corners (more than "
            f"{_MAX_INFERRED}; noise or a round aperture?); pass n_blades"
        )
    if inferred and rms > 0.05 * size:
        raise PupilPhotoError(
            f"inferred {n} blades but the sides fit poorly (RMS {rms:.2f} px); pass n_blades"
        )
    if not np.all(np.isfinite(verts)) or _area(verts) == 0:
        raise PupilPhotoError("polygon fit failed (degenerate sides)")

    # (row, col) → (x right, y up), counter-clockwise, centroid at the origin
    pc = _area_centroid(verts)
    xy = np.stack([verts[:, 1] - pc[1], -(verts[:, 0] - pc[0])], axis=1)
    if _area(xy) < 0:
        xy = xy[::-1]
    theta = np.arctan2(xy[:, 1], xy[:, 0])
    r = np.hypot(xy[:, 0], xy[:, 1])
    # order by angle, first vertex nearest the regular-polygon rotation
    order = np.argsort(np.mod(theta, 2 * np.pi))
    xy, theta, r = xy[order], theta[order], r[order]
    k = np.arange(n)
    rot = np.angle(np.mean(np.exp(1j * (theta - 2 * np.pi * k / n) * n))) / n
    rot = float(np.mod(rot, 2 * np.pi / n))
    first = int(np.argmin(np.abs(np.angle(np.exp(1j * (theta - rot))))))
    xy = np.roll(xy, -first, axis=0)
    px = float(pixel_size)
    out = xy * px
    out.setflags(write=False)
    return PupilPolygon(
        vertices=out,
        circumradius=float(np.mean(r) * px),
        rotation=rot,
        n_blades=n,
        n_blades_inferred=inferred,
        centroid_px=(float(pc[0]), float(pc[1])),
        residual_rms_px=float(rms),
    )


# ---------------------------------------------------------------------------- helpers


def _area(p: np.ndarray) -> float:
    """Signed shoelace area of a closed polygon (first point not repeated)."""
    x, y = p[:, 0], p[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def _area_centroid(p: np.ndarray) -> np.ndarray:
    x, y = p[:, 0], p[:, 1]
    x1, y1 = np.roll(x, -1), np.roll(y, -1)
    cr = x * y1 - x1 * y
    a = 0.5 * np.sum(cr)
    if a == 0:
        return p.mean(axis=0)
    return np.array([np.sum((x + x1) * cr), np.sum((y + y1) * cr)]) / (6 * a)


def _aperture_contour(img: np.ndarray) -> np.ndarray:
    """Sub-pixel outline (k, 2) (row, col) of the aperture region."""
    from scipy import ndimage
    from skimage import filters, measure

    if float(img.max() - img.min()) <= 0:
        raise PupilPhotoError("no aperture found: the image is uniform")
    t = float(filters.threshold_otsu(img))
    region = None
    for bright in (True, False):
        mask = img > t if bright else img <= t
        lab, nlab = ndimage.label(mask)
        if nlab == 0:
            continue
        border = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
        sizes = np.bincount(lab.ravel(), minlength=nlab + 1)
        sizes[0] = 0
        sizes[border] = 0
        best = int(np.argmax(sizes))
        if sizes[best] > 0 and (region is None or sizes[best] > region[1]):
            region = (ndimage.binary_fill_holes(lab == best), int(sizes[best]), bright)
    if region is None or region[1] < 50:
        raise PupilPhotoError(
            "no aperture found: no region of at least 50 pixels on either side of the Otsu "
            "threshold lies inside the image without touching its border"
        )
    mask, _, bright = region
    # Contour level halfway between the aperture's and the background's intensity (the
    # 50 % point of a blurred edge): medians of the two Otsu classes in a box around the
    # aperture (dominated by pixels far from the edge, so the blur does not bias them).
    rows, cols = np.nonzero(mask)
    pad = int(0.5 * math.sqrt(mask.sum() / math.pi)) + 4
    box = (
        slice(max(rows.min() - pad, 0), rows.max() + pad + 1),
        slice(max(cols.min() - pad, 0), cols.max() + pad + 1),
    )
    sub, msub = img[box], mask[box]
    outer = ~ndimage.binary_dilation(msub, iterations=2) & ((sub > t) != bright)
    inner = ndimage.binary_erosion(msub, iterations=2)
    if inner.sum() < 10 or outer.sum() < 10:
        raise PupilPhotoError("aperture too small to fit (fewer than ~10 pixels across)")
    bg = float(np.median(sub[outer]))
    level = 0.5 * (float(np.median(sub[inner])) + bg)
    # Trace only this aperture: everything outside a margin around it is background.
    zone = ndimage.binary_dilation(mask, iterations=8)
    work = np.where(zone, img, bg)
    work = np.pad(work, 1, constant_values=bg)
    cs = [c - 1.0 for c in measure.find_contours(work, level) if len(c) > 3]
    closed = [c for c in cs if np.allclose(c[0], c[-1])]
    if not closed:
        raise PupilPhotoError("no closed outline of the aperture found")
    c = max(closed, key=lambda c: abs(_area(c[:-1])))[:-1]
    if abs(_area(c)) < 0.5 * mask.sum():
        raise PupilPhotoError("aperture outline does not enclose the aperture region")
    return c


def _turning(p: np.ndarray) -> np.ndarray:
    """Exterior turning angle at each vertex of a closed polygon (radians, signed)."""
    d_in = p - np.roll(p, 1, axis=0)
    d_out = np.roll(p, -1, axis=0) - p
    a = np.arctan2(d_out[:, 1], d_out[:, 0]) - np.arctan2(d_in[:, 1], d_in[:, 0])
    return np.angle(np.exp(1j * a))


def _clean_corners(contour: np.ndarray, idx: np.ndarray, size: float) -> np.ndarray:
    """Drop near-straight corners and merge corners closer than a fraction of the size."""
    idx = np.array(sorted(set(int(i) for i in idx)))
    changed = True
    while changed and len(idx) > 3:
        changed = False
        p = contour[idx]
        turn = np.abs(_turning(p))
        seg = np.hypot(*(np.roll(p, -1, axis=0) - p).T)
        i = int(np.argmin(turn))
        if turn[i] < math.radians(12):
            idx = np.delete(idx, i)
            changed = True
            continue
        j = int(np.argmin(seg))
        if seg[j] < max(0.1 * size, 0.3 * float(np.median(seg))):
            idx = _merge_corners(contour, idx, j)
            changed = True
    return idx


def _merge_corners(contour: np.ndarray, idx: np.ndarray, j: int) -> np.ndarray:
    """Replace corners j and j + 1 (two corners of one rounded vertex) by the contour
    point between them farthest from the centroid."""
    a, b = int(idx[j]), int(idx[(j + 1) % len(idx)])
    span = np.arange(a, b + 1) if b > a else np.r_[a : len(contour), 0 : b + 1]
    cen = contour.mean(axis=0)
    best = int(span[int(np.argmax(np.hypot(*(contour[span] - cen).T)))])
    rest = np.delete(idx, [j, (j + 1) % len(idx)]).tolist()
    return np.array(sorted(set(rest + [best])))


def _candidate_corners(contour: np.ndarray, size: float, n: int | None) -> np.ndarray:
    """Indices into ``contour`` of the polygon's corners (n of them when n is given)."""
    from skimage.measure import approximate_polygon

    def corners_at(tol: float) -> np.ndarray:
        ap = approximate_polygon(np.vstack([contour, contour[:1]]), tolerance=tol)[:-1]
        # map the simplified points back to contour indices (they are contour points)
        d = np.hypot(*(contour[None, :, :] - ap[:, None, :]).transpose(2, 0, 1))
        return _clean_corners(contour, np.argmin(d, axis=1), size)

    # Start DP at a point far from any corner would be ideal; DP keeps the start point,
    # which the cleaning step removes when it is not a corner.
    if n is None:
        return corners_at(0.05 * size)
    # n known: search the tolerance that leaves n corners
    lo, hi = 0.002 * size, 0.5 * size
    best = None
    for _ in range(40):
        mid = math.sqrt(lo * hi)
        c = corners_at(mid)
        if len(c) == n:
            return c
        if len(c) > n:
            lo = mid
            best = c if best is None or len(c) < len(best) else best
        else:
            hi = mid
    if best is None or len(best) < n:
        raise PupilPhotoError(f"could not find {n} corners on the aperture outline")
    # too many: drop the corners with the smallest turning angle until n remain
    while len(best) > n:
        best = np.delete(best, int(np.argmin(np.abs(_turning(contour[best])))))
    return best


def _line_fit(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Total-least-squares line: (point, unit direction)."""
    m = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - m, full_matrices=False)
    return m, vt[0]


def _intersect(p1, d1, p2, d2) -> np.ndarray:
    a = np.array([d1, -d2]).T
    t = np.linalg.solve(a, p2 - p1)
    return p1 + t[0] * d1


def _fit_sides(contour: np.ndarray, corners: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Fit a line to each side between consecutive corners (trimmed near the corners),
    intersect consecutive lines; then reassign points to the fitted sides (away from the
    vertices) and refit, twice. Returns vertices (n, 2) (row, col), the RMS residual
    (px) and the unit side directions (n, 2)."""
    k = len(contour)
    n = len(corners)

    def side_points(a: int, b: int, trim: float) -> np.ndarray:
        span = np.arange(a, b) if b > a else np.r_[a:k, 0:b]
        m = len(span)
        cut = int(trim * m)
        sel = span[cut : m - cut] if m - 2 * cut >= 3 else span
        return contour[sel]

    lines = [side_points(int(corners[i]), int(corners[(i + 1) % n]), 0.2) for i in range(n)]
    fits = [_line_fit(p) for p in lines]
    for _ in range(2):
        verts = np.array(
            [_intersect(*fits[i - 1], *fits[i]) for i in range(n)]
        )  # vertex i between side i-1 and side i
        # reassign contour points to sides by the polygon's own sides, away from vertices
        sides_pts = []
        for i in range(n):
            a, b = verts[i], verts[(i + 1) % n]
            d = b - a
            length = float(np.hypot(*d))
            u = d / length
            t = (contour - a) @ u
            dist = np.abs((contour - a) @ np.array([-u[1], u[0]]))
            ok = (t > 0.15 * length) & (t < 0.85 * length) & (dist < 0.1 * length)
            sides_pts.append(contour[ok] if ok.sum() >= 3 else lines[i])
        fits = [_line_fit(p) for p in sides_pts]
    verts = np.array([_intersect(*fits[i - 1], *fits[i]) for i in range(n)])
    res = np.concatenate([(p - m) @ np.array([-d[1], d[0]]) for p, (m, d) in zip(sides_pts, fits)])
    # side directions, oriented along the contour from corner i to corner i + 1
    chords = contour[np.roll(corners, -1)] - contour[corners]
    dirs = np.array([d if d @ c >= 0 else -d for (_, d), c in zip(fits, chords)])
    return verts, float(np.sqrt(np.mean(res**2))), dirs
