"""The residuals of an image fit: the targets (pixels, spike profiles), the residual
function of one capture or several (the stars of a field: one ``lax.map`` where their
windows are alike), the flux and background in closed form (variable projection) and
the Jacobian's block structure over several captures."""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ._centred import fine_factor, image_from_centred, image_from_psf, optics_fixed
from ._data import FitData, _angle_from, _polar
from ._model import ImageModel
from ._params import FitInputError
from ._programs import _light_key


class _PixelTarget:
    """The residuals (model − data)/σ on the data's used pixels."""

    kind = "pixels"
    #: what a trace of :meth:`__call__` depends on besides its arrays (:mod:`._programs`)
    signature = ("pixels",)

    def __init__(self, data: FitData):
        self.data = data
        self.img = jnp.asarray(data.image)
        self.wgt = jnp.asarray(np.where(data.mask, 1.0 / data.sigma, 0.0))
        self.n = int(data.mask.sum())
        self.size = int(data.image.size)  # residuals: every pixel (masked ones 0)

    @property
    def arrays(self):
        """The data this target compares with, as arrays a compiled program takes as
        arguments (not constants: a program then serves another σ, mask or star)."""
        return (self.img, self.wgt)

    def __call__(self, model_image, v, arrays=None):
        img, wgt = self.arrays if arrays is None else arrays
        return ((model_image - img) * wgt).ravel()

class SpikeProfiles:
    """The residuals of the spikes' angular profiles: around each spike direction
    (``directions``, degrees, [0, 180), from the data), the mean of r²(I − background)
    over the pixels between ``r_min`` and ``r_max`` data pixels of the star, in bins of
    ``bin_width`` degrees within ± ``half_width`` (a spike and its opposite one share
    bins), each window normalised to unit sum, for data and model alike; weighted by the
    data's σ propagated through the same sums. The same pixels and bins serve both, so
    the binning's own bias cancels and only the spikes' positions and shapes count, not
    their brightness: a stage on these residuals fits the rotation and the distortion of
    the pupil from the spikes' directions alone. ``centre`` (x, y data pixels from the
    top-left pixel's centre, y down) and ``background`` are held (from earlier stages)."""

    kind = "spikes"

    def __init__(self, data: FitData, centre, background, directions, *, r_min=12.0,
                 r_max=45.0, half_width=4.0, bin_width=0.25):
        h, w = data.image.shape
        r, th = _polar((h, w), (float(centre[0]), float(centre[1])))
        use = data.mask & (r >= r_min) & (r <= r_max)
        nb = int(round(2 * half_width / bin_width))
        rows, cols, vals, window = [], [], [], []
        b = 0
        for k, phi in enumerate(directions):
            off = _angle_from(th, phi)
            j = np.floor((off + half_width) / bin_width).astype(int)
            for jb in range(nb):
                sel = np.flatnonzero((use & (j == jb)).ravel())
                if sel.size == 0:
                    continue
                rows += [b] * sel.size
                cols += sel.tolist()
                vals += (r.ravel()[sel] ** 2 / sel.size).tolist()
                window.append(k)
                b += 1
        if b == 0 or len(set(window)) < len(directions):
            raise FitInputError("spike profiles: no pixel near a spike direction between "
                                f"r = {r_min} and {r_max} px; check the annulus.")
        mat = np.zeros((b, h * w))
        mat[rows, cols] = vals
        self.window = np.asarray(window)
        self.n_windows = len(directions)
        self.mat = jnp.asarray(mat)
        self.background = float(background)
        pd = mat @ (data.image - self.background).ravel()
        sums = np.bincount(self.window, pd, minlength=self.n_windows)
        if np.any(sums <= 0):
            raise FitInputError("spike profiles: a spike window has no positive signal; "
                                "check the directions and the annulus.")
        self.profile = pd / sums[self.window]
        sig = np.sqrt((mat**2) @ (data.sigma**2).ravel()) / sums[self.window]
        self.wgt = jnp.asarray(1.0 / np.maximum(sig, 1e-12 * sig.max()))
        self.data_profile = jnp.asarray(self.profile)
        self.n = self.size = b
        self.directions = [float(d) for d in directions]

    @property
    def signature(self):
        """What a trace of :meth:`__call__` depends on besides its arrays."""
        return ("profiles", self.n_windows)

    @property
    def arrays(self):
        """The data this target compares with (see :attr:`_PixelTarget.arrays`)."""
        return (self.mat, jnp.asarray(self.window), self.data_profile, self.wgt)

    def __call__(self, model_image, v, arrays=None):
        mat, window, profile, wgt = self.arrays if arrays is None else arrays
        pm = mat @ (model_image - v["background"]).ravel()
        sums = jax.ops.segment_sum(pm, window, self.n_windows)
        return (pm / sums[window] - profile) * wgt

def _residual_fn(model: ImageModel, data, target):
    """(values, arrays, psfs) → (residual vector, [model image of each capture]) for
    ``model`` on each of ``data``'s windows (a FitData or a list of them, one ``target``
    each); ``arrays``: each target's :attr:`~_PixelTarget.arrays` as traced arguments
    (None: the targets' own, as constants); ``psfs``: each capture's
    :func:`~._centred.centred_psf` where the optics are held (None: the PSF engine at
    every call)."""
    datas, targets = _as_list(data), _as_list(target)
    plans = [model.plan(model.padded_shape(d.image.shape), d.light) for d in datas]
    qs = [fine_factor(model, d.light) for d in datas]

    def image(vi, d, plan, q, psf, exposure):
        if psf is not None:
            return image_from_centred(model, vi, d.image.shape, psf, q, exposure=exposure)
        return model.image(vi, d.image.shape, plan, exposure=exposure, light=d.light)

    if alike_captures(datas, targets):
        return _mapped_residual_fn(model, datas, targets, image, plans[0], qs[0])

    def res(v, arrays=None, psfs=None):
        rs, ms = [], []
        for i, (d, t, plan) in enumerate(zip(datas, targets, plans)):
            vi = model.capture_values(v, i)
            m = image(vi, d, plan, qs[i], None if psfs is None else psfs[i], d.exposure)
            rs.append(t(m, vi, None if arrays is None else arrays[i]))
            ms.append(m)
        return (rs[0] if len(rs) == 1 else jnp.concatenate(rs)), ms

    return res

def alike_captures(datas, targets) -> bool:
    """Whether several captures' residuals can be one ``lax.map`` (the stars of a field
    in windows of one size, one band, residuals of one kind and size): one trace and
    one compiled body for all of them, however many, where an unrolled loop's trace and
    compile grow with each star (about 2 s a star and a stage on the Spitzer star)."""
    if len(datas) < 2:
        return False
    d0, t0 = datas[0], targets[0]

    def arrays_shape(t):
        return [(np.shape(a), a.dtype) for a in jax.tree_util.tree_leaves(t.arrays)]

    return all(d.image.shape == d0.image.shape and _light_key(d.light) == _light_key(d0.light)
               and type(t) is type(t0) and t.signature == t0.signature
               and t.size == t0.size and arrays_shape(t) == arrays_shape(t0)
               for d, t in zip(datas, targets))

def _mapped_residual_fn(model: ImageModel, datas, targets, image, plan, q):
    """:func:`_residual_fn` of captures :func:`alike_captures` finds alike: one
    ``lax.map`` over them, each capture's own values (``name@i``), data, exposure and
    centred PSF its slice of the stacked arguments; the residuals concatenated in the
    captures' order, and the model images. Where the captures' own values all act after
    the optics, their PSF is computed once per call and moved to each star."""
    n, t0, d0 = len(datas), targets[0], datas[0]
    per = list(model.per_capture)
    exposures = np.asarray([d.exposure for d in datas], float)
    # the stars' own values act after the optics (their centres, fluxes, backgrounds):
    # one PSF at the window's centre, the optics' shared values, serves them all, each
    # star moved by a phase ramp of its spectrum (image_from_psf)
    shared = optics_fixed(model, per)
    light = model.light if d0.light is None else d0.light

    def res(v, arrays=None, psfs=None):
        arrays = [t.arrays for t in targets] if arrays is None else arrays
        xs = ({k: jnp.stack([jnp.asarray(v[f"{k}@{i}"]) for i in range(n)]) for k in per},
              jax.tree_util.tree_map(lambda *a: jnp.stack(a), *arrays),
              None if psfs is None else jnp.stack(psfs), jnp.asarray(exposures))
        centre = None
        if psfs is None and shared:
            centre, _ = model.window_psf(v, d0.image.shape, plan, light, shift=False)

        def one(x):
            own, a, psf, exposure = x
            vi = {**v, **own}
            if centre is not None:
                m = image_from_psf(model, centre, vi, d0.image.shape, q, exposure,
                                   move=True)
            else:
                m = image(vi, d0, plan, q, psf, exposure)
            return t0(m, vi, a), m

        rs, ms = jax.lax.map(one, xs)
        return rs.reshape(-1), [ms[i] for i in range(n)]

    return res

def _as_list(x):
    return list(x) if isinstance(x, (list, tuple)) else [x]

def closed_form(r0, a):
    """(r0 + A β, β) at the β that minimises |r0 + A β|² (A: residuals × n), by the
    normal equations of the column-scaled A. Differentiable: the solver's Jacobian of
    the projected residual is the exact one (no Kaufman approximation)."""
    norm = jnp.sqrt(jnp.sum(a * a, axis=0))
    scale = jnp.where(norm > 0, norm, 1.0)
    an = a / scale
    beta = -jnp.linalg.solve(an.T @ an, an.T @ r0) / scale
    return r0 + a @ beta, beta

def projected(model: ImageModel, lin: Sequence[str], images, v1, arrays):
    """:func:`closed_form` of the ``lin`` values (:func:`_linear_parts`): where each is
    one capture's own (``flux@i``, ``background@i``) and the captures are alike (the
    stars of a field), one small solve per capture (``vmap``), whose columns are then
    block-diagonal: the same answer without the dense (pixels × 2 stars) matrix of all
    captures, which would grow as the square of the stars."""
    own = _own_names(lin, len(images))
    shapes = {(np.shape(m), tuple(np.shape(a) for a in arr)) for m, arr in zip(images, arrays)}
    if own is None or len(shapes) > 1:
        return closed_form(*_linear_parts(model, lin, images, v1, arrays))
    parts = [_linear_parts(model, names, [m], v1, [arr], captures=[i])
             for i, (names, m, arr) in enumerate(zip(own, images, arrays))]
    r, beta = jax.vmap(closed_form)(jnp.stack([p[0] for p in parts]),
                                    jnp.stack([p[1] for p in parts]))
    where = {q: (i, j) for i, names in enumerate(own) for j, q in enumerate(names)}
    return r.reshape(-1), jnp.stack([beta[where[q]] for q in lin])

def _own_names(lin: Sequence[str], n: int):
    """``lin`` grouped by capture (each capture's ``name@i`` in ``lin``'s order) where
    every name is one capture's own and each of the ``n`` captures has the same names;
    else None."""
    own: list[list[str]] = [[] for _ in range(n)]
    for q in lin:
        base, _, i = q.partition("@")
        if not i.isdigit() or int(i) >= n:
            return None
        own[int(i)].append(q)
    bases = [[q.split("@")[0] for q in names] for names in own]
    return own if n > 1 and all(b == bases[0] for b in bases) and bases[0] else None

def _linear_parts(model: ImageModel, lin: Sequence[str], images, v1, arrays, *,
                  captures: Sequence[int] | None = None):
    """(r0, A) of the pixel residuals as an affine function of the ``lin`` values, from
    each capture's model image at ``v1`` (those fluxes at 1, backgrounds at 0): the image
    is flux · (exposure · PSF) + background, so the flux's column is the image less its
    background, the background's the weights, over the captures each name serves
    (``flux`` all of them, ``flux@i`` capture i). ``captures``: the captures' indices
    (default 0, 1, …), for a subset of them."""
    r0s, cols = [], [[] for _ in lin]
    captures = range(len(images)) if captures is None else captures
    for i, m, (img, wgt) in zip(captures, images, arrays):
        b = model.capture_values(v1, i)["background"]
        shape = m - b  # flux × exposure × PSF (flux 1 where projected)
        serves = [q == q.split("@")[0] or q == f"{q.split('@')[0]}@{i}" for q in lin]
        kinds = {q.split("@")[0] for q, ok in zip(lin, serves) if ok}
        base = (0.0 if "flux" in kinds else shape) + (0.0 if "background" in kinds else b)
        r0s.append(((base - img) * wgt).ravel())
        for j, (q, ok) in enumerate(zip(lin, serves)):
            col = shape * wgt if q.split("@")[0] == "flux" else wgt * jnp.ones_like(m)
            cols[j].append(col.ravel() if ok else jnp.zeros(m.size))
    return jnp.concatenate(r0s), jnp.stack([jnp.concatenate(c) for c in cols], axis=1)

def column_blocks(model: ImageModel, free: Sequence[str], target, lin=(), *,
                  outputs: bool = False):
    """The Jacobian's block structure over several captures (the stars of a field), for
    :func:`difstar._lm.with_batched_jacobian`'s ``blocks``: each of ``free``'s capture
    (``name@i``; −1 for a shared name) and each residual's, in ``target``'s order (with
    ``outputs``, also each capture's model image's); None where nothing is gained (one
    capture, no per-capture name) or the structure does not hold (a name of ``lin``
    taken in closed form shared by the captures couples their residuals)."""
    targets = _as_list(target)
    per = set(model.per_capture)

    def owner(k):
        base, _, i = k.partition("@")
        return int(i) if i and base in per else -1

    if len(targets) < 2 or any(owner(q) < 0 for q in lin):
        return None
    owners = [owner(k) for k in free]
    if all(o < 0 for o in owners):
        return None
    rows = np.repeat(np.arange(len(targets), dtype=np.int32), [t.size for t in targets])
    return owners, ((rows, [np.int32(i) for i in range(len(targets))]) if outputs
                    else rows)
