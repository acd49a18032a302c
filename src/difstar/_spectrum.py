"""Spectral weighting: source spectra × channel sensitivities (× lens transmission) →
per-channel wavelength weights, and a small set of wavelengths per channel chosen to an
accuracy target.

Units: wavelengths in metres everywhere in difstar's API (colour-science's nm are converted
at the boundary). Spectra are relative (any constant factor cancels once a channel's
weights are normalised); unnormalised channel weights keep the ratios between channels,
which is what white balance and φ0 describe.

A *source* may be given as
  - a temperature in kelvin (number): a blackbody, :func:`blackbody`;
  - a name in ``colour.SDS_ILLUMINANTS`` ("A", "D50", "D65", "E", "LED-B3", ...):
    :func:`illuminant`;
  - a ``colour.SpectralDistribution`` (wavelengths in nm);
  - a pair ``(wavelengths_m, values)``: a user table, :func:`user_spectrum`;
  - a callable ``f(wavelengths_m) -> values``.
*Sensitivities* may be given as
  - a name in ``colour.MSDS_CAMERA_SENSITIVITIES`` (e.g. "Nikon 5100 (NPL)");
  - a path to a rawtoaces camera JSON (:func:`difstar.io._sensitivity.load_spectral_sensitivity`);
  - a ``colour.MultiSpectralDistributions`` / ``RGB_CameraSensitivities`` (nm);
  - a pair ``(wavelengths_m, values (n, c))``;
  - a callable ``f(wavelengths_m) -> (n, c)``;
  - ``None``: one flat channel (sensitivity 1), for a broadband monochrome PSF.
Tabulated sensitivities are zero outside their tabulated range (interpolated linearly
inside); tabulated sources raise outside theirs.

Everything here is NumPy (concrete, outside jit) except :func:`blackbody` and
:func:`channel_weights`, which also accept JAX values (a traced temperature or lens
transmission) so the weights can be differentiated.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np
import scipy.special

from ._validate import MAX_SPECTRUM_SAMPLES, MAX_WAVELENGTHS, InputError, check_number
from .io._sensitivity import load_spectral_sensitivity

# CODATA 2018 exact constants
_H = 6.62607015e-34  # J s
_C = 299792458.0  # m / s
_K = 1.380649e-23  # J / K
_C2 = _H * _C / _K  # second radiation constant, m K
# x = c2 / (λ T) at the peak of B_λ: the root of (x − 5) e^x + 5 = 0
_X_PEAK = 4.965114231744276
WIEN_B = _C2 / _X_PEAK  # Wien's displacement constant, 2.897771955e-3 m K

DENSE_STEP = 5e-9  # the dense reference grid's spacing, metres
VISIBLE = (380e-9, 780e-9)


# --- sources -------------------------------------------------------------------------


def blackbody(wavelengths: Any, temperature: Any, *, absolute: bool = False) -> Any:
    """Planck's law per unit wavelength at ``wavelengths`` (metres) and ``temperature``
    (kelvin).

    Relative (default): B_λ(λ, T) / B_λ(λ_max, T), 1 at Wien's peak λ_max = b / T,

        (λ_max/λ)⁵ (e^{x_max} − 1) / (e^{c2/(λT)} − 1),   x_max = 4.965114231744276,

    computed without overflow or cancellation (expm1). ``absolute=True``: the spectral
    radiance 2hc²/λ⁵ / (e^{c2/(λT)} − 1) in W sr⁻¹ m⁻³ (per metre of wavelength).
    NumPy or JAX: differentiable w.r.t. the temperature and the wavelengths.
    """
    xp = jnp if _is_jax(wavelengths, temperature) else np
    lam = xp.asarray(wavelengths, dtype=float)
    t = xp.asarray(temperature, dtype=float)
    x = _C2 / (lam * t)
    if absolute:
        return 2 * _H * _C**2 / lam**5 / xp.expm1(x)
    lam_max = WIEN_B / t
    return (lam_max / lam) ** 5 * (math.expm1(_X_PEAK) / xp.expm1(x))


def _is_jax(*a) -> bool:
    import jax  # noqa: PLC0415

    return any(isinstance(v, jax.Array) for v in a)


def _nm(wavelengths_m) -> np.ndarray:
    return np.asarray(wavelengths_m, dtype=np.float64) * 1e9


def _check_wavelengths(wavelengths, name="wavelengths") -> np.ndarray:
    size = math.prod(np.shape(wavelengths))  # before a copy is made
    if size > MAX_SPECTRUM_SAMPLES:
        raise InputError(
            f"{name}: {size} wavelengths; give at most {MAX_SPECTRUM_SAMPLES} (a 0.01 nm "
            "grid over the visible has 40000).")
    wl = np.asarray(wavelengths, dtype=np.float64)
    if wl.ndim != 1 or wl.size < 1:
        raise ValueError(
            f"{name} must be a 1-D array of wavelengths in metres; got shape {wl.shape}."
        )
    if not np.all(np.isfinite(wl)) or np.any(wl <= 0):
        raise ValueError(f"{name} must be finite and > 0 (metres).")
    if np.any(wl > 1e-4):
        raise ValueError(
            f"{name} must be in metres (e.g. 550e-9); got values up to {wl.max():g}, "
            "which look like nanometres."
        )
    return wl


def _sd_at(sd, wavelengths_m, what: str) -> np.ndarray:
    """A colour SpectralDistribution at wavelengths (metres), by its own interpolator;
    ValueError outside its tabulated range."""
    nm = _nm(wavelengths_m)
    lo, hi = float(sd.wavelengths[0]), float(sd.wavelengths[-1])
    if np.any(nm < lo - 1e-9) or np.any(nm > hi + 1e-9):
        raise ValueError(
            f"{what} is tabulated over {lo:g}–{hi:g} nm; wavelengths {nm.min():g}–{nm.max():g} "
            "nm reach outside it."
        )
    return np.asarray(sd[np.clip(nm, lo, hi)], dtype=np.float64)


def illuminant(name: str, wavelengths: Any) -> np.ndarray:
    """The relative spectral power of ``colour.SDS_ILLUMINANTS[name]`` at ``wavelengths``
    (metres), by colour-science's interpolation of its table. Names include "A" (tungsten,
    2856 K), "D50", "D65", "E" (equal energy), "FL2", and CIE's LED series "LED-B1" …
    "LED-B5" (phosphor-converted blue), "LED-BH1", "LED-RGB1", "LED-V1", "LED-V2".
    ValueError for an unknown name or wavelengths outside the table."""
    import colour  # noqa: PLC0415

    if not isinstance(name, str) or name not in colour.SDS_ILLUMINANTS:
        leds = sorted(k for k in colour.SDS_ILLUMINANTS if k.startswith("LED"))
        raise ValueError(
            f"illuminant {name!r} is not in colour.SDS_ILLUMINANTS (e.g. 'A', 'D50', 'D65', "
            f"'E', {', '.join(repr(k) for k in leds)})."
        )
    wl = _check_wavelengths(wavelengths)
    return _sd_at(colour.SDS_ILLUMINANTS[name], wl, f"illuminant {name!r}")


def user_spectrum(wl: Any, values: Any, wavelengths: Any, *, fill: float | None = None
                  ) -> np.ndarray:
    """A tabulated spectrum (``wl`` in metres, increasing; ``values`` ≥ 0, same length)
    linearly interpolated at ``wavelengths`` (metres). Outside the table: ValueError, or
    ``fill`` if given (e.g. 0.0)."""
    wl = _check_wavelengths(wl, "user_spectrum wl")
    v = np.asarray(values, dtype=np.float64)
    if v.shape != wl.shape or wl.size < 2:
        raise ValueError(
            f"user_spectrum: wl and values must be 1-D of the same length ≥ 2; got {wl.shape} "
            f"and {v.shape}."
        )
    if np.any(np.diff(wl) <= 0):
        raise ValueError("user_spectrum: wl must be strictly increasing.")
    if not np.all(np.isfinite(v)) or np.any(v < 0):
        raise ValueError("user_spectrum: values must be finite and ≥ 0.")
    x = _check_wavelengths(wavelengths)
    outside = (x < wl[0] * (1 - 1e-12)) | (x > wl[-1] * (1 + 1e-12))
    if np.any(outside) and fill is None:
        raise ValueError(
            f"user_spectrum: wavelengths {x.min():.4g}–{x.max():.4g} m reach outside the table "
            f"{wl[0]:.4g}–{wl[-1]:.4g} m; pass fill=0.0 to extend by a constant."
        )
    out = np.interp(x, wl, v)
    if np.any(outside):
        out = np.where(outside, fill, out)
    return out


def as_spectrum(source: Any) -> Callable[[np.ndarray], Any]:
    """A source specification (see the module docstring) → f(wavelengths_m) → values."""
    import colour  # noqa: PLC0415

    if callable(source) and not isinstance(source, colour.SpectralDistribution):
        return source
    if isinstance(source, bool):
        raise ValueError(f"not a source spectrum: {source!r}")
    if isinstance(source, (int, float, np.floating, np.integer)) or _is_jax(source):
        t = source
        if not _is_jax(t) and not (math.isfinite(float(t)) and float(t) > 0):
            raise ValueError(f"blackbody temperature must be finite and > 0 kelvin; got {t}.")
        return lambda wl: blackbody(wl, t)
    if isinstance(source, str):
        return lambda wl: illuminant(source, wl)
    if isinstance(source, colour.SpectralDistribution):
        return lambda wl: _sd_at(source, _check_wavelengths(wl), f"source {source.name!r}")
    if isinstance(source, Sequence) and len(source) == 2:
        wl, values = source
        return lambda x: user_spectrum(wl, values, x)
    raise ValueError(
        "source must be a temperature (K), an illuminant name, a colour.SpectralDistribution, "
        f"a (wavelengths_m, values) pair or a callable; got {type(source).__name__}."
    )


# --- sensitivities ---------------------------------------------------------------------


def _msds_function(msds) -> Callable[[np.ndarray], np.ndarray]:
    wl_m = np.asarray(msds.wavelengths, dtype=np.float64) * 1e-9
    values = np.asarray(msds.values, dtype=np.float64)
    return _table_function(wl_m, values)


def _table_function(wl_m, values) -> Callable[[np.ndarray], np.ndarray]:
    wl_m = _check_wavelengths(wl_m, "sensitivity wavelengths")
    values = np.asarray(values, dtype=np.float64)
    if values.ndim == 1:
        values = values[:, None]
    if values.shape[0] != wl_m.size and values.ndim == 2 and values.shape[1] == wl_m.size:
        values = values.T
    if values.shape[0] != wl_m.size or values.ndim != 2:
        raise ValueError(
            f"sensitivity values must be (n_wavelengths, channels); got {values.shape} for "
            f"{wl_m.size} wavelengths."
        )
    if np.any(np.diff(wl_m) <= 0):
        raise ValueError("sensitivity wavelengths must be strictly increasing.")
    if not np.all(np.isfinite(values)):
        raise ValueError("sensitivity values must be finite.")

    def f(x):
        x = np.asarray(x, dtype=np.float64)
        tol = 1e-9 * wl_m[-1]
        inside = (x >= wl_m[0] - tol) & (x <= wl_m[-1] + tol)
        cols = [np.interp(x, wl_m, values[:, c]) for c in range(values.shape[1])]
        return np.where(inside[:, None], np.stack(cols, axis=1), 0.0)

    f.support = (float(wl_m[0]), float(wl_m[-1]))  # type: ignore[attr-defined]
    f.channels = values.shape[1]  # type: ignore[attr-defined]
    return f


def as_sensitivities(sensitivities: Any) -> Callable[[np.ndarray], np.ndarray]:
    """A sensitivity specification (see the module docstring) → f(wavelengths_m) →
    (n, channels) values, zero outside the tabulated range. The returned function has
    ``support`` (metres, or None) and ``channels`` attributes where known."""
    import colour  # noqa: PLC0415

    if sensitivities is None:
        def flat(x):
            return np.ones((np.asarray(x).size, 1))
        flat.support = None  # type: ignore[attr-defined]
        flat.channels = 1  # type: ignore[attr-defined]
        return flat
    if isinstance(sensitivities, colour.MultiSpectralDistributions):
        return _msds_function(sensitivities)
    if isinstance(sensitivities, str) and sensitivities in colour.MSDS_CAMERA_SENSITIVITIES:
        return _msds_function(colour.MSDS_CAMERA_SENSITIVITIES[sensitivities])
    if isinstance(sensitivities, (str, Path)):
        p = Path(sensitivities)
        if not p.is_file():
            raise ValueError(
                f"sensitivities {str(sensitivities)!r} is neither a name in "
                f"colour.MSDS_CAMERA_SENSITIVITIES {tuple(colour.MSDS_CAMERA_SENSITIVITIES)} "
                "nor an existing rawtoaces JSON file."
            )
        return _msds_function(load_spectral_sensitivity(p))
    if callable(sensitivities):
        return sensitivities
    if isinstance(sensitivities, Sequence) and len(sensitivities) == 2:
        return _table_function(*sensitivities)
    raise ValueError(
        "sensitivities must be None, a colour.MSDS_CAMERA_SENSITIVITIES name, a rawtoaces "
        "JSON path, a colour MultiSpectralDistributions, a (wavelengths_m, values) pair or a "
        f"callable; got {type(sensitivities).__name__}."
    )


# --- weights ----------------------------------------------------------------------------


def trapezoid_weights(wavelengths: Any) -> np.ndarray:
    """Trapezoid-rule quadrature weights Δλ_i (metres) on increasing ``wavelengths``:
    half the distance between neighbours, half a step at each end. One wavelength: 1."""
    wl = _check_wavelengths(wavelengths)
    if wl.size == 1:
        return np.ones(1)
    if np.any(np.diff(wl) <= 0):
        raise ValueError("wavelengths must be strictly increasing.")
    w = np.zeros_like(wl)
    d = np.diff(wl) / 2
    w[:-1] += d
    w[1:] += d
    return w


class ChannelWeights(NamedTuple):
    """Per-channel spectral weights on ``wavelengths`` (metres, (n,)).

    weights: (c, n), source × sensitivity × transmission × Δλ (trapezoid), unnormalised;
    ``weights.sum(1)`` is each channel's relative response to the source (its ratios are
    what white balance undoes). normalised: (c, n), each row summing to 1 (the
    ``weights=`` of a broadband PSF).
    """

    wavelengths: Any
    weights: Any
    normalised: Any


def channel_weights(source: Any, sensitivities: Any, wavelengths: Any, transmission: Any = None
                    ) -> ChannelWeights:
    """Spectral weights per channel on ``wavelengths`` (metres, increasing, concrete).

    ``source``: values at ``wavelengths`` ((n,) array) or a source specification (module
    docstring). ``sensitivities``: a (c, n) array of values at ``wavelengths`` or a
    sensitivity specification. ``transmission``: None (1), a (n,) array, or a callable of
    wavelengths (metres), e.g. a lens's transmission curve.

    weights[c, i] = S(λ_i) s_c(λ_i) T(λ_i) Δλ_i with Δλ_i the trapezoid weights, so
    Σ_i weights[c, i] g(λ_i) is the trapezoid rule for ∫ S s_c T g dλ. JAX-traceable in
    source and transmission values (the wavelengths must be concrete).
    """
    wl = _check_wavelengths(wavelengths)
    n = wl.size
    if np.size(wl) > 1 and np.any(np.diff(wl) <= 0):
        raise ValueError("wavelengths must be strictly increasing.")
    s = _values_at(source, wl, as_spectrum)
    sens = sensitivities
    if isinstance(sens, np.ndarray) or _is_jax(sens):
        sens = jnp.asarray(sens) if _is_jax(sens) else np.asarray(sens, dtype=np.float64)
        if sens.ndim == 1:
            sens = sens[None, :]
        if sens.ndim != 2 or sens.shape[1] != n:
            raise ValueError(f"sensitivities must be (channels, {n}); got {sens.shape}.")
    else:
        sens = np.asarray(as_sensitivities(sens)(wl), dtype=np.float64).T  # (c, n)
    t = 1.0 if transmission is None else _values_at(transmission, wl, _transmission_function)
    xp = jnp if _is_jax(s, sens, t) else np
    s = xp.broadcast_to(xp.asarray(s, dtype=float), (n,))
    t = xp.broadcast_to(xp.asarray(t, dtype=float), (n,))
    w = sens * (s * t * trapezoid_weights(wl))[None, :]
    total = w.sum(axis=1, keepdims=True)
    if not _is_jax(total) and np.any(np.asarray(total) <= 0):
        raise ValueError(
            "a channel has no weight: source × sensitivity × transmission is zero over the "
            "wavelengths given."
        )
    return ChannelWeights(wl, w, w / total)


def _values_at(spec, wl, convert):
    """Arrays are values at ``wl``; anything else is a specification for ``convert``."""
    if isinstance(spec, np.ndarray) or _is_jax(spec):
        v = spec if _is_jax(spec) else np.asarray(spec, dtype=np.float64)
        if v.shape not in ((), (wl.size,)):
            raise ValueError(f"spectral values must have shape ({wl.size},); got {v.shape}.")
        return v
    return convert(spec)(wl)


def _transmission_function(t):
    if isinstance(t, (int, float)) and not isinstance(t, bool):
        return lambda wl: np.full(np.shape(wl), float(t))
    if callable(t):
        return t
    raise ValueError(
        "transmission must be None, a number, a (n,) array or a callable of wavelengths "
        f"(metres); got {type(t).__name__}."
    )


# --- choosing wavelengths -----------------------------------------------------------------


def airy_family(radii: Any = None, *, reference: float = 550e-9
                ) -> Callable[[np.ndarray], np.ndarray]:
    """Test functions g_r(λ): the in-focus Airy PSF of a circular pupil at fixed image
    radii r, as functions of wavelength, normalised to 1 at the peak for ``reference``:

        g_r(λ) = (λ_ref/λ)² [2 J1(v)/v]²,   v = π (r / (λ_ref N)) (λ_ref / λ),

    i.e. power per unit area on a fixed pixel grid (the 1/λ² is the peak's scaling).
    ``radii`` in units of λ_ref N (default 0 … 20 in steps of 0.05: core, first rings and
    the near halo, where a peak-relative error is largest). Returns f(λ) → (n, n_radii).
    """
    rho = np.arange(0.0, 20.0 + 1e-9, 0.05) if radii is None else np.asarray(radii, float)

    def g(wl):
        s = reference / np.asarray(wl, dtype=np.float64)[:, None]
        v = np.pi * rho[None, :] * s
        safe = np.where(v == 0, 1.0, v)
        a = np.where(v == 0, 1.0, 2 * scipy.special.j1(safe) / safe)
        return s**2 * a**2

    return g


def _check_node_count(k, field: str) -> int:
    """A wavelength count 1 … ``MAX_WAVELENGTHS`` (each is a PSF evaluation), naming
    ``field``."""
    return check_number(k, field, ge=1, le=MAX_WAVELENGTHS, integer=True,
                        fix="wavelengths per channel; each is a PSF evaluation")


def gauss_nodes(points: Any, masses: Any, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The k-point Gauss(–Christoffel) rule of a discrete measure Σ_i masses_i δ(λ − points_i)
    (masses ≥ 0): nodes (inside the points' range) and positive weights summing to
    Σ masses, exact for polynomials of degree ≤ 2k − 1. Lanczos (Stieltjes) with full
    reorthogonalisation, then Golub–Welsch. k = 1: the centroid."""
    _check_node_count(k, "gauss_nodes: k")
    x = np.asarray(points, dtype=np.float64)
    m = np.asarray(masses, dtype=np.float64)
    keep = m > 0
    x, m = x[keep], m[keep]
    if k < 1 or k > x.size:
        raise ValueError(f"k must be 1 … {x.size} (points with positive mass); got {k}.")
    mass = m.sum()
    lo, hi = x.min(), x.max()
    c, h = (hi + lo) / 2, max((hi - lo) / 2, np.finfo(float).tiny)
    t = (x - c) / h  # map to [−1, 1] for conditioning
    q = np.sqrt(m / mass)  # first Lanczos vector: √(mass) in the discrete inner product
    basis = [q]
    alpha, beta = [], []
    for i in range(k):
        v = t * basis[-1]
        a = basis[-1] @ v
        alpha.append(a)
        if i == k - 1:
            break
        for b in basis:  # full reorthogonalisation (twice is enough)
            v = v - (b @ v) * b
        for b in basis:
            v = v - (b @ v) * b
        nb = np.linalg.norm(v)
        beta.append(nb)
        basis.append(v / nb)
    jacobi = np.diag(alpha) + np.diag(beta, 1) + np.diag(beta, -1)
    nodes, vecs = np.linalg.eigh(jacobi)
    weights = mass * vecs[0] ** 2
    return c + h * nodes, weights


class WavelengthChoice(NamedTuple):
    """Wavelengths and weights per channel (tuples of 1-D arrays, one per channel;
    lengths may differ): Σ_k weights[c][k] = 1. ``errors``: (c,) the achieved error
    against the dense reference; ``table``: (c, k_max) the error with 1 … k_max
    wavelengths (NaN beyond where the search stopped)."""

    wavelengths: tuple
    weights: tuple
    errors: np.ndarray
    table: np.ndarray

    def padded(self) -> tuple[np.ndarray, np.ndarray]:
        """(c, K) wavelengths and weights, K the largest count; the shorter channels are
        padded with their last wavelength at weight 0."""
        k = max(len(w) for w in self.wavelengths)
        wl = np.stack([np.pad(w, (0, k - len(w)), mode="edge") for w in self.wavelengths])
        ws = np.stack([np.pad(w, (0, k - len(w))) for w in self.weights])
        return wl, ws


def dense_weights(source: Any, sensitivities: Any, *, band: Any = None, transmission: Any = None,
                  step: float = DENSE_STEP) -> ChannelWeights:
    """The dense reference: :func:`channel_weights` on a ``step`` (default 5 nm) grid over
    ``band`` (metres; default the sensitivities' tabulated range ∩ 380–780 nm, or
    380–780 nm)."""
    sens_f = as_sensitivities(sensitivities)
    if band is None:
        support = getattr(sens_f, "support", None)
        band = VISIBLE if support is None else (max(support[0], VISIBLE[0]),
                                                min(support[1], VISIBLE[1]))
    lo, hi = (float(b) for b in band)
    if not (0 < lo < hi and math.isfinite(hi)):
        raise ValueError(f"band must be (low, high) metres with 0 < low < high; got {band}.")
    step = check_number(step, "step", gt=0, fix="metres, e.g. 5e-9")
    if (hi - lo) / step > MAX_SPECTRUM_SAMPLES:
        raise InputError(
            f"step: {step:g} m over the band {lo:g}–{hi:g} m is {(hi - lo) / step:.3g} "
            f"wavelengths; give at most {MAX_SPECTRUM_SAMPLES} (a step >= "
            f"{(hi - lo) / MAX_SPECTRUM_SAMPLES:.3g} m, or a narrower band).")
    n = int(round((hi - lo) / step))
    wl = np.linspace(lo, lo + n * step, n + 1)
    wl = wl[wl <= hi * (1 + 1e-12)]
    return channel_weights(source, sens_f, wl, transmission)


def quadrature_error(nodes, weights, dense: ChannelWeights, channel: int,
                     test_function: Callable) -> float:
    """max over the family of |Σ_k w_k g(λ_k) − Σ_i W_i g(λ_i)| / max over the family of
    |Σ_i W_i g(λ_i)| (W: the channel's normalised dense weights): the error relative to
    the largest value (for the Airy family, the peak of the broadband PSF)."""
    ref = np.asarray(dense.normalised[channel]) @ test_function(dense.wavelengths)
    approx = np.asarray(weights) @ test_function(np.asarray(nodes))
    return float(np.max(np.abs(approx - ref)) / np.max(np.abs(ref)))


def choose_wavelengths(source: Any, sensitivities: Any, accuracy: float = 1e-3, *,
                       band: Any = None, transmission: Any = None,
                       test_function: Callable | None = None, max_wavelengths: int = 16,
                       step: float = DENSE_STEP) -> WavelengthChoice:
    """Per channel, the fewest wavelengths (and weights summing to 1) whose weighted sum
    of a test-function family matches the dense ``step`` (5 nm) sum to ``accuracy``.

    The rule for K wavelengths is the K-point Gauss rule of the channel's own dense
    spectral weight (source × sensitivity × transmission on the 5 nm grid,
    :func:`gauss_nodes`): nodes inside the band, positive weights, exact for every
    polynomial in λ of degree ≤ 2K − 1 against the dense sum. K = 1 is the channel's
    weighted mean wavelength (the trichromatic model's one wavelength per channel).
    K grows until :func:`quadrature_error` ≤ ``accuracy`` for ``test_function``
    (default :func:`airy_family` with the channel's mean wavelength as reference: the
    in-focus PSF at radii 0 … 20 λN, error relative to its peak). ValueError if
    ``max_wavelengths`` do not reach the target.

    ``source``, ``sensitivities``, ``transmission``: as in :func:`channel_weights`
    (specifications, not arrays); ``band``: as in :func:`dense_weights`.
    """
    if not (accuracy > 0):
        raise ValueError(f"accuracy must be > 0; got {accuracy}.")
    max_wavelengths = _check_node_count(max_wavelengths, "choose_wavelengths: max_wavelengths")
    dense = dense_weights(source, sensitivities, band=band, transmission=transmission,
                          step=step)
    wl = dense.wavelengths
    norm = np.asarray(dense.normalised)
    channels = norm.shape[0]
    table = np.full((channels, max_wavelengths), np.nan)
    out_wl, out_w, errors = [], [], []
    for c in range(channels):
        g = test_function
        if g is None:
            g = airy_family(reference=float(norm[c] @ wl))
        kmax = min(max_wavelengths, int(np.count_nonzero(norm[c] > 0)))
        for k in range(1, kmax + 1):
            nodes, weights = gauss_nodes(wl, norm[c], k)
            err = quadrature_error(nodes, weights, dense, c, g)
            table[c, k - 1] = err
            if err <= accuracy:
                break
        else:
            raise ValueError(
                f"channel {c}: {kmax} wavelengths reach an error of {err:.3g}, above the "
                f"accuracy target {accuracy:g}; raise max_wavelengths or the target."
            )
        out_wl.append(nodes)
        out_w.append(weights / weights.sum())
        errors.append(err)
    return WavelengthChoice(tuple(out_wl), tuple(out_w), np.asarray(errors), table)


def error_table(source: Any, sensitivities: Any, ks: Sequence[int] = tuple(range(1, 11)), *,
                band: Any = None, transmission: Any = None,
                test_function: Callable | None = None, step: float = DENSE_STEP
                ) -> np.ndarray:
    """(channels, len(ks)): the error of the K-point Gauss rule against the dense
    ``step`` sum, for each K in ``ks`` (same measure as :func:`choose_wavelengths`).
    Use it to report error against the number of wavelengths."""
    ks = [_check_node_count(k, f"error_table: ks[{i}]") for i, k in enumerate(ks)]
    dense = dense_weights(source, sensitivities, band=band, transmission=transmission,
                          step=step)
    wl = dense.wavelengths
    norm = np.asarray(dense.normalised)
    out = np.zeros((norm.shape[0], len(ks)))
    for c in range(norm.shape[0]):
        g = test_function or airy_family(reference=float(norm[c] @ wl))
        for i, k in enumerate(ks):
            nodes, weights = gauss_nodes(wl, norm[c], k)
            out[c, i] = quadrature_error(nodes, weights, dense, c, g)
    return out


__all__ = [
    "ChannelWeights",
    "WIEN_B",
    "WavelengthChoice",
    "airy_family",
    "as_sensitivities",
    "as_spectrum",
    "blackbody",
    "channel_weights",
    "choose_wavelengths",
    "dense_weights",
    "error_table",
    "gauss_nodes",
    "illuminant",
    "quadrature_error",
    "trapezoid_weights",
    "user_spectrum",
]
