"""Independent reference PSFs for the tests: NumPy/SciPy float64, no difstar code.

Everything here is written from the physics, not from difstar's sources, so that a test
comparing ``difstar.psf`` with these functions compares two independent computations.

Conventions (the contract of ``difstar.psf``)
---------------------------------------------
* Window (H, W), pixel pitch p. Pixel (H//2, W//2) is centred on the optical axis; rows run
  down and y points up: row k is at y = −(k − H//2)·p, column k at x = (k − W//2)·p.
  A pixel covers [x − p/2, x + p/2] × [y − p/2, y + p/2] (fill factor 1).
* Pupil coordinates ξ = (ξ, η) in metres, x right, y up; polygon vertices counter-clockwise;
  a rotation is counter-clockwise from +x.
* Field (Fresnel form, exit pupil to sensor distance z_R, in-focus image at
  z_i = z_R − Δz):

      U(x) = ∫_P exp(i φ(ξ)) exp(+2πi x·ξ / (λ z_R)) dξ,
      φ(ξ) = k W(ξ) + 2π OPD(ξ)/λ,   W(ξ) = ½ (1/z_i − 1/z_R) |ξ|²,   k = 2π/λ,

  and the intensity, a density per m² in the image plane, I(x) = |U(x)|² / (λ² z_R² A_P)
  with A_P the pupil's area: by Parseval ∫ I dA = 1 over the infinite plane, so I dA is the
  fraction of the power through the pupil that lands on dA. With this sign of the kernel,
  beyond focus (Δz > 0) the geometric blur is the pupil turned by 180° (rays that crossed
  the axis draw it); the intensity in focus does not depend on the sign.
  ``KERNEL_SIGN`` holds the sign of the kernel's exponent.
* Pixel values: ``sampling="point"`` = I(pixel centre) · p²; ``sampling="pixel"`` =
  ∫∫_pixel I dA, by a Gauss–Legendre product rule over the pixel's square. The intensity
  is band-limited (its spectrum, the OTF, vanishes beyond D/(λ z_R), D the pupil's
  diameter), so the rule's error is that of exp(2πi ν x) at |ν| ≤ D p/(λ z_R) cycles per
  pixel; :func:`pixel_nodes_for` picks the node count from that bound with a wide margin
  and the self-checks in ``test_references_agree`` confirm convergence.
"""

from __future__ import annotations

import math
from functools import cache

import numpy as np
import scipy.special

#: sign of the exponent of the Fresnel kernel exp(±2πi x·ξ/(λ z_R)) (see module docstring)
KERNEL_SIGN = +1.0

H_PLANCK = 6.62607015e-34  # J s
C_LIGHT = 299792458.0  # m/s
K_BOLTZMANN = 1.380649e-23  # J/K


# --- quadrature ----------------------------------------------------------------------------


@cache
def gauss_legendre(n: int) -> tuple[np.ndarray, np.ndarray]:
    """n-point Gauss–Legendre nodes and weights on [−1, 1] (float64)."""
    x, w = np.polynomial.legendre.leggauss(int(n))
    x.setflags(write=False)
    w.setflags(write=False)
    return x, w


def gl_panels(a: float, b: float, panels: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Composite Gauss–Legendre rule on [a, b]: ``panels`` equal panels of n nodes each."""
    x, w = gauss_legendre(n)
    edges = np.linspace(a, b, panels + 1)
    half = 0.5 * np.diff(edges)
    mid = 0.5 * (edges[:-1] + edges[1:])
    nodes = (mid[:, None] + half[:, None] * x[None, :]).ravel()
    weights = (half[:, None] * w[None, :]).ravel()
    return nodes, weights


def pixel_nodes_for(cycles_per_pixel: float, extra: int = 0) -> int:
    """Gauss–Legendre nodes a side for the integral over one pixel of a function whose
    spectrum vanishes beyond ``cycles_per_pixel``: the n-point rule integrates
    exp(iωt) on [−1, 1] with error ~ (e ω / 4n)^{2n}; ω = π ν here. n ≥ 0.9 ω + 6 puts that
    below 1e-12 for every ω of interest."""
    omega = math.pi * abs(float(cycles_per_pixel))
    return int(math.ceil(0.9 * omega + 6)) + int(extra)


# --- the window -----------------------------------------------------------------------------


def pixel_centres(shape, pixel_pitch) -> tuple[np.ndarray, np.ndarray]:
    """(x of each column (W,), y of each row (H,)) in metres, per the module's convention."""
    h, w = shape
    x = (np.arange(w) - w // 2) * float(pixel_pitch)
    y = -(np.arange(h) - h // 2) * float(pixel_pitch)
    return x, y


def _node_axis(centres: np.ndarray, pitch: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Nodes (len·n,) and weights (n,) of an n-point rule over each pixel (weights sum to p)."""
    t, w = gauss_legendre(n)
    nodes = (centres[:, None] + 0.5 * pitch * t[None, :]).ravel()
    return nodes, 0.5 * pitch * w


def integrate_over_pixels(intensity, shape, pixel_pitch, *, sampling: str, nodes: int,
                          rows=None, cols=None, chunk: int = 2_000_000) -> np.ndarray:
    """Pixel values of a density ``intensity(x, y)`` (per m², vectorised on broadcast arrays).

    sampling="point": I(centre) · p²; "pixel": ∫∫_pixel I by an n × n Gauss–Legendre rule.
    Without rows/cols: the whole (H, W) window. With rows and cols (equal-length integer
    arrays): those pixels only, a 1-D array.
    """
    p = float(pixel_pitch)
    xc, yc = pixel_centres(shape, p)
    if sampling not in ("point", "pixel"):
        raise ValueError(f"sampling must be 'point' or 'pixel'; got {sampling!r}")
    if rows is not None:
        rows = np.asarray(rows, int)
        cols = np.asarray(cols, int)
        if sampling == "point":
            return intensity(xc[cols], yc[rows]) * p * p
        t, w = gauss_legendre(nodes)
        off = 0.5 * p * t
        ww = (0.5 * p) ** 2 * (w[:, None] * w[None, :])
        if hasattr(intensity, "grid"):  # separable kernel: one small matrix product a pixel
            return np.array([np.sum(intensity.grid(xc[c] + off, yc[r] + off) * ww)
                             for r, c in zip(rows, cols)])
        X = xc[cols][:, None, None] + off[None, None, :]
        Y = yc[rows][:, None, None] + off[None, :, None]
        return np.einsum("kij,ij->k", intensity(X, Y), ww)
    if sampling == "point":
        out = np.empty(shape)
        step = max(1, chunk // max(1, shape[1]))
        for r0 in range(0, shape[0], step):
            out[r0:r0 + step] = intensity(xc[None, :], yc[r0:r0 + step, None]) * p * p
        return out
    xs, wx = _node_axis(xc, p, nodes)
    h, wdt = shape
    out = np.empty(shape)
    step = max(1, chunk // (len(xs) * nodes))
    for r0 in range(0, h, step):
        r1 = min(h, r0 + step)
        ys, wy = _node_axis(yc[r0:r1], p, nodes)
        vals = intensity(xs[None, :], ys[:, None]).reshape(r1 - r0, nodes, wdt, nodes)
        out[r0:r1] = np.einsum("aibj,i,j->ab", vals, wy, wx)
    return out


# --- a. polygons in focus: the exact transform ---------------------------------------------


def regular_polygon_vertices(n: int, circumradius: float, rotation: float = 0.0) -> np.ndarray:
    """(n, 2) vertices counter-clockwise, the first at angle ``rotation`` from +x."""
    th = rotation + 2 * np.pi * np.arange(n) / n
    return circumradius * np.stack([np.cos(th), np.sin(th)], axis=-1)


def polygon_area(vertices) -> float:
    """Signed (shoelace) area; > 0 for counter-clockwise vertices."""
    v0 = np.asarray(vertices, float)
    v1 = np.roll(v0, -1, axis=0)
    return 0.5 * float(np.sum(v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]))


def polygon_diameter(vertices) -> float:
    v = np.asarray(vertices, float)
    return float(np.max(np.hypot(*(v[:, None, :] - v[None, :, :]).transpose(2, 0, 1))))


def polygon_ft(vertices: np.ndarray, kx: np.ndarray, ky: np.ndarray) -> np.ndarray:
    """Exact ∫_P exp(-i k·x) dA of a polygon (Lee & Mittra 1983), NumPy float64.

    By the divergence theorem with F = i k e^{-ik·x}/|k|²:
    Σ_edges (i/|k|²)(k·n_e) L_e e^{-ik·m_e} sinc(k·t_e L_e / 2); the area at k = 0.
    """
    v0 = np.asarray(vertices, float)
    v1 = np.roll(v0, -1, axis=0)
    kx = np.asarray(kx, float)
    ky = np.asarray(ky, float)
    k2 = kx * kx + ky * ky
    out = np.zeros(np.broadcast(kx, ky).shape, complex)
    for a, b in zip(v0, v1):
        d = b - a
        length = np.hypot(*d)
        tx, ty = d / length
        nx, ny = ty, -tx
        mx, my = (a + b) / 2
        kn = kx * nx + ky * ny
        kt = kx * tx + ky * ty
        out += kn * length * np.exp(-1j * (kx * mx + ky * my)) * np.sinc(kt * length / (2 * np.pi))
    with np.errstate(invalid="ignore", divide="ignore"):
        out = 1j * out / k2
    area = 0.5 * np.sum(v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1])
    return np.where(k2 == 0, area, out)


def polygon_intensity_focus(vertices, *, wavelength, z):
    """I(x, y) per m², in focus: |F_P(2π x/(λz))|² / (λ² z² A) (Lee–Mittra F_P).

    In focus U(x) = F_P(−KERNEL_SIGN·2π x/(λ z)); |F_P(−k)| = |F_P(k)| for a real pupil."""
    v = np.asarray(vertices, float)
    area = polygon_area(v)
    s = 2 * np.pi / (wavelength * z)

    def intensity(x, y):
        amp = polygon_ft(v, s * np.asarray(x, float), s * np.asarray(y, float))
        return np.abs(amp) ** 2 / ((wavelength * z) ** 2 * area)

    return intensity


def polygon_psf_exact(vertices, *, wavelength, z, pixel_pitch, shape, sampling: str = "point",
                      nodes: int | None = None):
    """In-focus PSF of a polygonal pupil on a (H, W) window, centred at (H//2, W//2):
    the fraction of the pupil's power on each pixel (point: I(centre)·p²; pixel: ∫∫ I over
    the pixel by ``nodes``² Gauss–Legendre nodes, by default from the band limit
    D p/(λ z) cycles per pixel). Σ over the infinite grid = 1 (Parseval)."""
    if nodes is None:
        nodes = pixel_nodes_for(polygon_diameter(vertices) * pixel_pitch / (wavelength * z))
    return integrate_over_pixels(polygon_intensity_focus(vertices, wavelength=wavelength, z=z),
                                 shape, pixel_pitch, sampling=sampling, nodes=nodes)


# --- b. circular pupils with a radial phase: the Hankel integral ---------------------------


def defocus_from_waves(waves, *, wavelength, radius, z_image) -> float:
    """Δz giving W020 = ½(1/z_i − 1/z_R) R² = ``waves`` · λ at the pupil's edge (z_i = z_R − Δz)."""
    w020 = waves * wavelength
    z_i = 1.0 / (1.0 / z_image + 2.0 * w020 / radius**2)
    return z_image - z_i


def waves_from_defocus(defocus, *, wavelength, radius, z_image) -> float:
    """W020/λ = ½(1/z_i − 1/z_R) R²/λ."""
    z_i = z_image - defocus
    return 0.5 * (1.0 / z_i - 1.0 / z_image) * radius**2 / wavelength


def noll_radial(j: int, u):
    """Rotationally symmetric unit-RMS Noll Zernike terms at u = ρ/R (j = 1, 4, 11, 22, 37)."""
    u2 = np.asarray(u, float) ** 2
    if j == 1:
        return np.ones_like(u2)
    if j == 4:
        return math.sqrt(3) * (2 * u2 - 1)
    if j == 11:
        return math.sqrt(5) * (6 * u2**2 - 6 * u2 + 1)
    if j == 22:
        return math.sqrt(7) * (20 * u2**3 - 30 * u2**2 + 12 * u2 - 1)
    if j == 37:
        return 3.0 * (70 * u2**4 - 140 * u2**3 + 90 * u2**2 - 20 * u2 + 1)
    raise ValueError(f"noll_radial: j={j} is not a rotationally symmetric term here")


def radial_phase(*, wavelength, radius, z_image=None, defocus=0.0, waves=None, noll=None):
    """φ(u), u = ρ/R ∈ [0, 1], radians: the exact Fresnel defocus k·½(1/z_i − 1/z_R)ρ²
    (from ``defocus`` = Δz, or ``waves`` = W020/λ) plus 2π/λ Σ c_j Z_j(u) for ``noll`` =
    {j: metres RMS} (j rotationally symmetric)."""
    a = 0.0
    if waves is not None:
        a = 2 * np.pi * waves
    elif defocus:
        a = 2 * np.pi * waves_from_defocus(defocus, wavelength=wavelength, radius=radius,
                                           z_image=z_image)
    noll = dict(noll or {})

    def phase(u):
        u = np.asarray(u, float)
        out = a * u * u
        for j, c in noll.items():
            out = out + (2 * np.pi / wavelength) * c * noll_radial(j, u)
        return out

    return phase


def _max_slope(phase, n: int = 4097) -> float:
    """max |dφ/du| on [0, 1], numerically (radians per unit u)."""
    u = np.linspace(0.0, 1.0, n)
    return float(np.max(np.abs(np.diff(phase(u)))) * (n - 1))


def hankel_field(r, *, radius, wavelength, z, phase=None, r_max=None):
    """U(r) = 2π ∫₀^R e^{iφ(ρ/R)} J₀(2π ρ r / (λ z)) ρ dρ for every r (metres), complex.

    Composite Gauss–Legendre in ρ, 20 nodes per panel, a panel for every two cycles of
    the integrand (phase slope plus J₀'s rate up to ``r_max``): error far below 1e-12."""
    r = np.asarray(r, float)
    R = float(radius)
    r_max = float(np.max(np.abs(r))) if r_max is None else float(r_max)
    slope = 0.0 if phase is None else _max_slope(phase)
    cycles = slope / (2 * np.pi) + r_max * R / (wavelength * z)
    panels = int(math.ceil(cycles / 2)) + 2
    rho, w = gl_panels(0.0, R, panels, 20)
    f = rho * w * (1.0 if phase is None else np.exp(1j * phase(rho / R)))
    b = 2 * np.pi * rho / (wavelength * z)
    out = np.empty(r.shape, complex)
    flat = r.ravel()
    o = out.reshape(-1)
    step = max(1, 4_000_000 // len(rho))
    for i in range(0, flat.size, step):
        o[i:i + step] = scipy.special.j0(flat[i:i + step, None] * b[None, :]) @ f
    return 2 * np.pi * out


def circle_intensity_radial(r, *, radius, wavelength, z, phase=None, r_max=None):
    """I(r) per m² = |U(r)|² / (π R² λ² z²) (Hankel integral; ∫ I dA = 1)."""
    u = hankel_field(r, radius=radius, wavelength=wavelength, z=z, phase=phase, r_max=r_max)
    return np.abs(u) ** 2 / (np.pi * radius**2 * (wavelength * z) ** 2)


def airy_intensity_radial(r, *, radius, wavelength, z):
    """Analytic Airy density per m²: (π R²/(λ z)²) [2 J₁(v)/v]², v = 2π R r/(λ z)."""
    v = 2 * np.pi * radius * np.asarray(r, float) / (wavelength * z)
    with np.errstate(invalid="ignore", divide="ignore"):
        a = np.where(v == 0, 1.0, 2 * scipy.special.j1(v) / np.where(v == 0, 1.0, v))
    return np.pi * radius**2 / (wavelength * z) ** 2 * a * a


def airy_encircled_energy(r, *, radius, wavelength, z):
    """Fraction of the power within radius r: 1 − J₀(v)² − J₁(v)² (Rayleigh)."""
    v = 2 * np.pi * radius * np.asarray(r, float) / (wavelength * z)
    return 1 - scipy.special.j0(v) ** 2 - scipy.special.j1(v) ** 2


class RadialInterpolant:
    """Piecewise Chebyshev interpolant of a smooth radial function f(r) on [0, r_max]:
    panels of width ``h``, ``n`` Chebyshev (first-kind) points each. f is evaluated once,
    vectorised, at all points; the interpolant is then evaluated by Clenshaw's recurrence.
    For a function of exponential type τ (the intensity: τ = 2π ν_c, ν_c = D/(λ z) its band
    limit) the error on a panel is ~ (e τ h / 4n)^n: h = 1/ν_c, n = 24 keep it near 1e-14
    (checked against direct evaluation in ``test_references_agree``)."""

    def __init__(self, f, r_max: float, h: float, n: int = 20):
        self.h = float(h)
        self.panels = int(math.ceil(r_max / h)) + 1
        self.n = int(n)
        k = np.arange(n)
        t = np.cos(np.pi * (k + 0.5) / n)  # first-kind Chebyshev points on [−1, 1]
        r = (np.arange(self.panels)[:, None] + 0.5 * (1 + t[None, :])) * self.h
        vals = np.asarray(f(r.ravel()), float).reshape(self.panels, n)
        # c_j = (2/n) Σ_k f_k T_j(t_k), c_0 halved
        T = np.cos(np.pi * np.outer(np.arange(n), k + 0.5) / n)  # T_j(t_k)
        c = (2.0 / n) * vals @ T.T
        c[:, 0] *= 0.5
        self.coef = c

    def __call__(self, r):
        r = np.asarray(r, float)
        idx = np.clip((r / self.h).astype(np.int64), 0, self.panels - 1)
        t = 2 * (r / self.h - idx) - 1
        c = self.coef[idx]  # (..., n)
        b1 = np.zeros_like(t)
        b2 = np.zeros_like(t)
        for j in range(self.n - 1, 0, -1):
            b1, b2 = 2 * t * b1 - b2 + c[..., j], b1
        return t * b1 - b2 + c[..., 0]


def radial_psf(intensity_radial, *, shape, pixel_pitch, sampling: str, band_cycles_per_m: float,
               rows=None, cols=None, nodes: int | None = None, h: float | None = None):
    """Pixel values of a rotationally symmetric density I(r) (centred on the axis).

    I(r) is tabulated by :class:`RadialInterpolant` out to the window's farthest corner
    (panels of h = 1/ν_c, 24 points each, where ν_c is the intensity's band limit in
    cycles/m: the interpolant's error is ~1e-14 of the peak, even with 50 waves of defocus), then
    integrated per pixel (``integrate_over_pixels``)."""
    p = float(pixel_pitch)
    hgt, wdt = shape
    r_max = math.hypot(max(wdt // 2, wdt - wdt // 2) + 1, max(hgt // 2, hgt - hgt // 2) + 1) * p
    if h is None:
        h = 1.0 / band_cycles_per_m
    interp = RadialInterpolant(intensity_radial, r_max, h, n=24)
    if nodes is None:
        nodes = pixel_nodes_for(band_cycles_per_m * p)

    def intensity(x, y):
        return interp(np.hypot(x, y))

    return integrate_over_pixels(intensity, shape, p, sampling=sampling, nodes=nodes,
                                 rows=rows, cols=cols)


def circle_psf(*, radius, wavelength, z, pixel_pitch, shape, sampling: str = "pixel",
               phase=None, nodes: int | None = None, rows=None, cols=None):
    """PSF (fraction of power per pixel) of a circular pupil of ``radius`` with a radial
    phase φ(ρ/R) (radians; see :func:`radial_phase`), sensor at z = z_R: the Hankel
    integral :func:`circle_intensity_radial`, point-sampled or pixel-integrated.
    ``phase=None``: the analytic Airy pattern (no quadrature in ρ)."""
    hgt, wdt = shape
    p = float(pixel_pitch)
    r_max = math.hypot(wdt // 2 + 2, hgt // 2 + 2) * p
    if phase is None:
        def f(r):
            return airy_intensity_radial(r, radius=radius, wavelength=wavelength, z=z)
    else:
        def f(r):
            return circle_intensity_radial(r, radius=radius, wavelength=wavelength, z=z,
                                           phase=phase, r_max=r_max)
    band = 2 * radius / (wavelength * z)
    return radial_psf(f, shape=shape, pixel_pitch=p, sampling=sampling,
                      band_cycles_per_m=band, nodes=nodes, rows=rows, cols=cols)


# --- c. polygons with defocus or any phase: quadrature of the Fresnel integral ------------


def _fan_rule(vertices, n_s: int, n_t: int):
    """Nodes (N, 2) and weights (N,) of a product Gauss–Legendre rule over the polygon, as
    a fan of triangles (c, v_i, v_{i+1}) from the vertex mean c (the polygon must be
    star-shaped from c, e.g. convex): ξ = c + s[(v_i − c) + t(v_{i+1} − v_i)], s, t ∈ [0, 1],
    dA = s |det(v_i − c, v_{i+1} − v_i)| ds dt (exact for the map; smooth integrand)."""
    v = np.asarray(vertices, float)
    c = v.mean(axis=0)
    xs, ws = gauss_legendre(n_s)
    xt, wt = gauss_legendre(n_t)
    s = 0.5 * (xs + 1)
    t = 0.5 * (xt + 1)
    ws = 0.5 * ws
    wt = 0.5 * wt
    pts, wts = [], []
    for a, b in zip(v, np.roll(v, -1, axis=0)):
        e1 = a - c
        e2 = b - a
        jac = abs(e1[0] * e2[1] - e1[1] * e2[0])
        edge = e1[None, None, :] + t[None, :, None] * e2[None, None, :]
        p = c[None, None, :] + s[:, None, None] * edge
        pts.append(p.reshape(-1, 2))
        wts.append((jac * s[:, None] * ws[:, None] * wt[None, :]).ravel())
    return np.concatenate(pts), np.concatenate(wts)


def polygon_fresnel_intensity(vertices, *, wavelength, z_image, defocus=0.0, phase=None,
                              x_max: float, order: float = 1.0):
    """I(x, y) per m² for a polygonal pupil with exact Fresnel defocus and an optional
    extra phase ``phase(ξ, η)`` (radians, pupil coordinates in metres), by Gauss–Legendre
    quadrature of U(x) = ∫_P e^{iφ(ξ)} e^{±2πi x·ξ/(λ z_R)} dξ over a fan of triangles.

    Nodes a side per triangle from the largest phase change across a triangle: the
    defocus slope k |1/z_i − 1/z_R| ρ_max, the kernel's 2π x_max/(λ z_R) (``x_max``: the
    farthest image point asked for) and the extra phase's slope (estimated on a grid):
    n = ⌈0.9 ω⌉ + 12 with ω half the phase change, × ``order`` (the self-check raises it)."""
    v = np.asarray(vertices, float)
    area = polygon_area(v)
    lam, zr = float(wavelength), float(z_image)
    z_i = zr - float(defocus)
    a = (2 * np.pi / lam) * 0.5 * (1.0 / z_i - 1.0 / zr)  # φ_defocus = a |ξ|²
    c = v.mean(axis=0)
    ext = float(np.max(np.hypot(*(v - c).T)))  # triangle extent from c
    rho_max = float(np.max(np.hypot(*v.T)))
    slope = 2 * abs(a) * rho_max + 2 * np.pi * x_max * math.sqrt(2) / (lam * zr)
    if phase is not None:
        g = np.linspace(-rho_max, rho_max, 257)
        X, Y = np.meshgrid(g, g)
        ph = phase(X, Y)
        gy, gx = np.gradient(ph, g, g)
        slope += float(np.max(np.hypot(gx, gy)))
    omega = 0.5 * slope * ext
    n = int(math.ceil(order * (0.9 * omega + 12)))
    pts, wts = _fan_rule(v, n, n)
    phi = a * (pts[:, 0] ** 2 + pts[:, 1] ** 2)
    if phase is not None:
        phi = phi + phase(pts[:, 0], pts[:, 1])
    f = wts * np.exp(1j * phi)
    s = KERNEL_SIGN * 2 * np.pi / (lam * zr)

    def intensity(x, y):
        x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
        xf, yf = x.ravel(), y.ravel()
        u = np.empty(xf.size, complex)
        step = max(1, 3_000_000 // len(f))
        for i in range(0, xf.size, step):
            arg = s * (xf[i:i + step, None] * pts[None, :, 0]
                       + yf[i:i + step, None] * pts[None, :, 1])
            u[i:i + step] = np.exp(1j * arg) @ f
        return (np.abs(u) ** 2 / ((lam * zr) ** 2 * area)).reshape(x.shape)

    def grid(xs, ys):
        """I on the outer grid (len(ys), len(xs)): e^{is(xξ+yη)} = e^{isxξ} e^{isyη}, so
        U = (E_y · f) E_xᵀ, a matrix product (far fewer exponentials)."""
        ex = np.exp(1j * s * np.asarray(xs, float)[:, None] * pts[None, :, 0])
        ey = np.exp(1j * s * np.asarray(ys, float)[:, None] * pts[None, :, 1])
        u = (ey * f[None, :]) @ ex.T
        return np.abs(u) ** 2 / ((lam * zr) ** 2 * area)

    intensity.nodes = n
    intensity.grid = grid
    return intensity


def _sampled(rows, cols, shape, pixel_pitch):
    """(rows, cols) as integer arrays, and the farthest sampled point's radius plus a
    pixel (how far the quadrature's intensity must reach)."""
    rows = np.asarray(rows, int)
    cols = np.asarray(cols, int)
    xc, yc = pixel_centres(shape, pixel_pitch)
    return rows, cols, float(np.max(np.hypot(xc[cols], yc[rows]))) + pixel_pitch


def polygon_fresnel_psf(vertices, rows, cols, *, wavelength, z_image, defocus=0.0,
                        pixel_pitch, shape, sampling: str = "pixel", phase=None,
                        nodes: int | None = None, order: float = 1.0):
    """Pixel values (fraction of power) at the pixels (rows[k], cols[k]) of an (H, W)
    window for a polygonal pupil with Fresnel defocus Δz (and an optional extra phase),
    by quadrature of the Fresnel integral (:func:`polygon_fresnel_intensity`)."""
    rows, cols, x_max = _sampled(rows, cols, shape, pixel_pitch)
    inten = polygon_fresnel_intensity(vertices, wavelength=wavelength, z_image=z_image,
                                      defocus=defocus, phase=phase, x_max=x_max, order=order)
    if nodes is None:
        nodes = pixel_nodes_for(polygon_diameter(vertices) * pixel_pitch / (wavelength * z_image))
    return integrate_over_pixels(inten, shape, pixel_pitch, sampling=sampling, nodes=nodes,
                                 rows=rows, cols=cols)


def sample_pixels(shape, *, spokes_deg=(), radii_px=(), n_random: int = 0, seed: int = 0,
                  core: int = 2):
    """A deterministic set of pixels (rows, cols): the (2·core+1)² block round the centre,
    points on rays at the angles ``spokes_deg`` (counter-clockwise from +x, y up) and
    radii ``radii_px``, and ``n_random`` uniformly drawn pixels; duplicates removed."""
    h, w = shape
    pts = set()
    for dr in range(-core, core + 1):
        for dc in range(-core, core + 1):
            pts.add((h // 2 + dr, w // 2 + dc))
    for ang in spokes_deg:
        th = math.radians(ang)
        for r in radii_px:
            col = w // 2 + int(round(r * math.cos(th)))
            row = h // 2 - int(round(r * math.sin(th)))
            if 0 <= row < h and 0 <= col < w:
                pts.add((row, col))
    rng = np.random.default_rng(seed)
    for _ in range(n_random):
        pts.add((int(rng.integers(0, h)), int(rng.integers(0, w))))
    pts = sorted(pts)
    return np.array([p[0] for p in pts]), np.array([p[1] for p in pts])


# --- c'. a circular pupil with any phase (coma, astigmatism): polar quadrature -----------


def noll_nm(j: int) -> tuple[int, int]:
    """Noll index j ≥ 1 → (n, m); m > 0 a cos(mθ) term (even j), m < 0 a sin(|m|θ) term
    (odd j). Within radial order n, |m| rises with j (Noll 1976)."""
    j = int(j)
    if j < 1:
        raise ValueError("Noll index j >= 1")
    n = 0
    while (n + 1) * (n + 2) // 2 < j:
        n += 1
    k = j - n * (n + 1) // 2 - 1
    am = 2 * ((k + 1) // 2) if n % 2 == 0 else 2 * (k // 2) + 1
    if am == 0:
        return n, 0
    return n, (am if j % 2 == 0 else -am)


def zernike_noll(j: int, rho, theta):
    """Unit-RMS Noll Zernike term Z_j at normalised radius ρ and angle θ (from +x towards
    +y): √(n+1) R_n^0, or √(2(n+1)) R_n^|m| cos(mθ) (m > 0) / sin(|m|θ) (m < 0), with
    R_n^m(ρ) = Σ_s (−1)^s (n−s)! / (s! ((n+m)/2−s)! ((n−m)/2−s)!) ρ^{n−2s}."""
    n, m = noll_nm(j)
    am = abs(m)
    rho = np.asarray(rho, float)
    rad = np.zeros_like(rho)
    for s_ in range((n - am) // 2 + 1):
        c = ((-1) ** s_ * math.factorial(n - s_)
             / (math.factorial(s_) * math.factorial((n + am) // 2 - s_)
                * math.factorial((n - am) // 2 - s_)))
        rad = rad + c * rho ** (n - 2 * s_)
    if m == 0:
        return math.sqrt(n + 1) * rad
    ang = np.cos(am * theta) if m > 0 else np.sin(am * theta)
    return math.sqrt(2 * (n + 1)) * rad * ang


def zernike_phase_xy(coefficients, *, wavelength, radius):
    """phase(x, y) = 2π/λ Σ_j c_j Z_j(r/R, θ) (radians; c_j in metres RMS), pupil metres."""
    coefficients = dict(coefficients)

    def phase(x, y):
        x = np.asarray(x, float)
        y = np.asarray(y, float)
        rho = np.hypot(x, y) / radius
        th = np.arctan2(y, x)
        out = np.zeros(np.broadcast(x, y).shape)
        for j, c in coefficients.items():
            out = out + (2 * np.pi / wavelength) * c * zernike_noll(j, rho, th)
        return out

    return phase


def disc_fresnel_intensity(radius, *, wavelength, z_image, defocus=0.0, phase=None,
                           x_max: float, order: float = 1.0):
    """I(x, y) per m² for a circular pupil with Fresnel defocus and any extra phase
    ``phase(ξ, η)`` (radians), by quadrature in polar coordinates: composite Gauss–Legendre
    in ρ (20 nodes per two cycles of the integrand), the trapezoid rule in θ (periodic, so
    spectrally accurate) with M ≥ 1.5 k R + 2 max|φ| + 32 points, k R = 2π x_max R/(λ z_R)
    the kernel's largest phase at the rim. Normalised as the module says."""
    R_ = float(radius)
    lam, zr = float(wavelength), float(z_image)
    z_i = zr - float(defocus)
    a = (2 * np.pi / lam) * 0.5 * (1.0 / z_i - 1.0 / zr)
    kr = 2 * np.pi * x_max * math.sqrt(2) * R_ / (lam * zr)
    phimax, slope = abs(a) * R_**2, 2 * abs(a) * R_
    if phase is not None:
        g = np.linspace(-R_, R_, 257)
        X, Y = np.meshgrid(g, g)
        inside = np.hypot(X, Y) <= R_
        ph = phase(X, Y)
        gy, gx = np.gradient(ph, g, g)
        phimax += float(np.max(np.abs(ph[inside])))
        slope += float(np.max(np.hypot(gx, gy)[inside]))
    cycles = (kr + slope * R_) / (2 * np.pi)
    rho, wr = gl_panels(0.0, R_, int(math.ceil(order * (cycles / 2 + 2))), 20)
    m_th = int(math.ceil(order * (1.5 * kr + 2 * phimax + 32)))
    th = 2 * np.pi * np.arange(m_th) / m_th
    X = (rho[:, None] * np.cos(th)[None, :]).ravel()
    Y = (rho[:, None] * np.sin(th)[None, :]).ravel()
    W = (wr[:, None] * rho[:, None] * np.full(m_th, 2 * np.pi / m_th)[None, :]).ravel()
    phi = a * (X * X + Y * Y)
    if phase is not None:
        phi = phi + phase(X, Y)
    f = W * np.exp(1j * phi)
    s = KERNEL_SIGN * 2 * np.pi / (lam * zr)
    area = np.pi * R_**2

    def intensity(x, y):
        x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
        xf, yf = x.ravel(), y.ravel()
        u = np.empty(xf.size, complex)
        step = max(1, 3_000_000 // len(f))
        for i in range(0, xf.size, step):
            arg = s * (xf[i:i + step, None] * X[None, :] + yf[i:i + step, None] * Y[None, :])
            u[i:i + step] = np.exp(1j * arg) @ f
        return (np.abs(u) ** 2 / ((lam * zr) ** 2 * area)).reshape(x.shape)

    def grid(xs, ys):
        """I on the outer grid (len(ys), len(xs)) by a matrix product (see the polygon's)."""
        ex = np.exp(1j * s * np.asarray(xs, float)[:, None] * X[None, :])
        ey = np.exp(1j * s * np.asarray(ys, float)[:, None] * Y[None, :])
        u = (ey * f[None, :]) @ ex.T
        return np.abs(u) ** 2 / ((lam * zr) ** 2 * area)

    intensity.grid = grid
    return intensity


def disc_fresnel_psf(radius, rows, cols, *, wavelength, z_image, defocus=0.0, pixel_pitch,
                     shape, sampling: str = "pixel", phase=None, nodes: int | None = None,
                     order: float = 1.0):
    """Pixel values at (rows[k], cols[k]) for a circular pupil with any phase
    (:func:`disc_fresnel_intensity`), point-sampled or pixel-integrated."""
    rows, cols, x_max = _sampled(rows, cols, shape, pixel_pitch)
    inten = disc_fresnel_intensity(radius, wavelength=wavelength, z_image=z_image,
                                   defocus=defocus, phase=phase, x_max=x_max, order=order)
    if nodes is None:
        nodes = pixel_nodes_for(2 * radius * pixel_pitch / (wavelength * z_image))
    return integrate_over_pixels(inten, shape, pixel_pitch, sampling=sampling, nodes=nodes,
                                 rows=rows, cols=cols)


# --- d. broadband: blackbody weights -------------------------------------------------------


def planck(wavelength, temperature):
    """Spectral radiance B_λ(T) = 2hc²/λ⁵ / (exp(hc/(λ k T)) − 1), W sr⁻¹ m⁻³."""
    lam = np.asarray(wavelength, float)
    return (2 * H_PLANCK * C_LIGHT**2 / lam**5
            / np.expm1(H_PLANCK * C_LIGHT / (lam * K_BOLTZMANN * temperature)))


def blackbody_weights(wavelengths, temperature):
    """Weights ∝ B_λ(T) at equally spaced wavelengths (power per wavelength bin), Σ = 1."""
    b = planck(wavelengths, temperature)
    return b / b.sum()


def broadband_airy_psf(*, radius, wavelengths, weights, z, pixel_pitch, shape,
                       sampling: str = "pixel"):
    """Σ_i w_i · Airy_i (normalised weights), pixel-integrated (or point-sampled): the
    fraction of the power on each pixel for a polychromatic source in focus. The weighted
    sum of the analytic radial densities is itself radial; it is tabulated once (band
    limit of the shortest wavelength) and integrated over the pixels."""
    lams = np.asarray(wavelengths, float)
    wts = np.asarray(weights, float)
    wts = wts / wts.sum()

    def f(r):
        out = 0.0
        for lam, wt in zip(lams, wts):
            out = out + wt * airy_intensity_radial(r, radius=radius, wavelength=lam, z=z)
        return out

    band = 2 * radius / (lams.min() * z)
    return radial_psf(f, shape=shape, pixel_pitch=pixel_pitch, sampling=sampling,
                      band_cycles_per_m=band)


# --- energy of a radial density over a rectangle (independent check of pixel sums) --------


def _arc_inside(r: float, x0, x1, y0, y1) -> float:
    """Angle (radians) of the circle of radius r about the origin inside the rectangle."""
    br = [0.0, 2 * np.pi]
    for c in (x0, x1):
        if abs(c) < r:
            a = math.acos(c / r)
            br += [a % (2 * np.pi), (-a) % (2 * np.pi)]
    for c in (y0, y1):
        if abs(c) < r:
            a = math.asin(c / r)
            br += [a % (2 * np.pi), (np.pi - a) % (2 * np.pi)]
    br = np.unique(br)
    mid = 0.5 * (br[:-1] + br[1:])
    inside = ((r * np.cos(mid) >= x0) & (r * np.cos(mid) <= x1)
              & (r * np.sin(mid) >= y0) & (r * np.sin(mid) <= y1))
    return float(np.sum(np.diff(br)[inside]))


def radial_energy_in_rectangle(intensity_radial, x0, x1, y0, y1, *, h: float, n: int = 20):
    """∫∫_rectangle I(|x|) dA = ∫₀^{r_corner} I(r) r θ_in(r) dr, θ_in the arc inside: a 1-D
    composite Gauss–Legendre rule between breakpoints at the sides' and corners' distances
    (where θ_in has square-root kinks, smoothed by a cubic change of variable). For
    checking pixel sums."""
    corners = [math.hypot(a, b) for a in (x0, x1) for b in (y0, y1)]
    bps = sorted({0.0, *(abs(c) for c in (x0, x1, y0, y1)), *corners})
    nodes, weights = [], []
    for a, b in zip(bps[:-1], bps[1:]):
        if b <= a:
            continue
        # θ_in has square-root kinks at the breakpoints: r = a + (b − a)(3t² − 2t³)
        # (zero slope at both ends) makes the integrand smooth in t
        k = max(1, int(math.ceil(2 * (b - a) / h)))
        t, w = gl_panels(0.0, 1.0, k, n)
        nodes.append(a + (b - a) * (3 * t**2 - 2 * t**3))
        weights.append(w * (b - a) * 6 * t * (1 - t))
    r = np.concatenate(nodes)
    w = np.concatenate(weights)
    th = np.array([_arc_inside(ri, x0, x1, y0, y1) for ri in r])
    return float(np.sum(w * intensity_radial(r) * r * th))


def window_rectangle(shape, pixel_pitch):
    """(x0, x1, y0, y1): the window's outer edges in metres."""
    h, w = shape
    p = float(pixel_pitch)
    xc, yc = pixel_centres(shape, p)
    return xc[0] - p / 2, xc[-1] + p / 2, yc[-1] - p / 2, yc[0] + p / 2


# --- helpers kept from tests/helpers.py -----------------------------------------------------


def airy_psf(r, *, wavelength, f_number):
    """Airy intensity at radius r (metres), peak 1: [2 J1(x)/x]², x = π r / (λ N)."""
    x = np.pi * np.asarray(r, float) / (wavelength * f_number)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = (2 * scipy.special.j1(x) / x) ** 2
    return np.where(x == 0, 1.0, out)


def fd_grad(f, x, eps):
    """Central finite difference of scalar f at scalar x."""
    return (f(x + eps) - f(x - eps)) / (2 * eps)


def rel_rms(a, b) -> float:
    """||a − b||₂ / ||b||₂ (b the truth)."""
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))
