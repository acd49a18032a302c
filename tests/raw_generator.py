"""An independent RAW camera: NumPy captures of a curved-blade iris with spherical
aberration and defocus, written without any of difstar's model code.

This is the truth a RAW fit is checked against. Everything here is written from the
physics (the conventions of ``tests/references.py``), with its own choices wherever
difstar's model makes one:

* **Lens**: a thick lens focused by extension (paper Eq. 6, closed form), the exit pupil
  ``f·m_p + δz`` in front of the sensor, Δz = s' − s_i; the source's image scale from the
  chief ray through the exit pupil.
* **Pupil**: ``n`` blades; vertex k at radius R, angle rotation + 2πk/n; the edge from
  vertex k to k+1 is a circular arc of curvature c/R bulging outwards (c = 1: the
  circumscribed circle). The pupil is sampled by *point-in-shape tests* on a fine
  sub-grid of each pupil cell (``pupil_supersample``² points per cell) — not by
  difstar's Green's-theorem edge coverage — and each cell holds the mean of the complex
  pupil function over its points inside, so edge cells carry the phase of their
  covered part.
* **Wavefront**: exp(i k (W_dz + W_ab)), W_dz = ½(1/z_i − 1/z_R)|ξ|², W_ab =
  c11·√5·(6ρ⁴ − 6ρ² + 1) with ρ = |ξ| / R_zernike (Noll 11, unit RMS over that circle).
* **Field**: a zero-padded FFT with the kernel exp(+2πi x·ξ/(λ z_R)), divided on its
  principal period by the transform of the cells' point means (a Dirichlet kernel); the
  intensity on a sub-pixel grid (``pixel_supersample``² samples per pixel), normalised
  so that it sums to the fraction of the pupil's power, then **summed over each pixel's
  area** (box integration, no sinc model).
* **Source**: a uniform disc of radius r_s in the object plane, its geometric image a
  disc of radius |M|·r_s drawn by sub-pixel point tests, convolved with the intensity.
* **Radiometry**: the geometric image's irradiance is L·A/z_R² (A the pupil's area,
  L = 1) over the disc's image of radius |M|·r_s: a change of aperture changes the
  signal as in a camera, and a change of focus spreads the same power differently.
* **Sensor**: linear photo-electrons (Poisson), Gaussian read noise, offset by a black
  level, quantised to DN and clipped at the white level; its own Bayer layout.

``make_captures`` returns the mosaics and the truth; ``python tests/raw_generator.py
--out DIR`` writes a campaign (DNG captures + a RAW-fit manifest) to a new folder.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

CHANNELS = "RGB"


@dataclass(frozen=True)
class Lens:
    focal_length: float = 0.050
    principal_separation: float = 0.0
    pupil_magnification: float = 1.0


@dataclass(frozen=True)
class Iris:
    n: int = 9
    circumradius: float = 2.2e-3
    curvature: float = 0.5
    rotation: float = 0.1
    spherical: float = 100e-9  # Noll 11 coefficient, metres RMS over zernike_radius
    zernike_radius: float = 2.2e-3


@dataclass(frozen=True)
class Sensor:
    pixel_pitch: float = 3.917e-6
    pattern: str = "GBRG"
    wavelengths: tuple = (610e-9, 535e-9, 460e-9)
    # photo-electrons per unit of relative irradiance × second, per channel
    quantum_scale: tuple = (3.6e18, 4.8e18, 2.8e18)
    gain_e_per_dn: float = 1.5
    read_noise_dn: float = 2.5
    black_level: int = 512
    white_level: int = 16383


@dataclass(frozen=True)
class Configuration:
    name: str
    focus_distance: float
    object_distance: float
    exposure_times: tuple
    source_position: tuple  # (row, col) in the frame, pixels (pixel centres at integers)


@dataclass(frozen=True)
class Campaign:
    lens: Lens = field(default_factory=Lens)
    iris: Iris = field(default_factory=Iris)
    sensor: Sensor = field(default_factory=Sensor)
    source_radius: float = 0.25e-3
    frame: tuple = (160, 160)
    configurations: tuple = ()
    pupil_supersample: int = 8
    pixel_supersample: int = 4
    fft_size: int = 2048


# ------------------------------------------------------------------------ geometry

def lens_geometry(lens: Lens, focus_distance: float, object_distance: float) -> dict:
    """Paper Eq. 6 in closed form: extension, z_R (exit pupil to sensor), z_i (exit
    pupil to the in-focus image), Δz = z_R − z_i and the image scale M (chief ray)."""
    f, zp = lens.focal_length, lens.principal_separation
    big_l = focus_distance - zp
    s_prime = 0.5 * (big_l - math.sqrt(big_l * big_l - 4 * f * big_l))
    ext = s_prime - f
    s_obj = object_distance - zp - s_prime
    s_img = 1.0 / (1.0 / f - 1.0 / s_obj)
    z_r = f * lens.pupil_magnification + ext
    dz = s_prime - s_img
    z_i = z_r - dz
    m = -(s_img / s_obj) * (z_r / z_i)
    return {"z_R": z_r, "z_i": z_i, "defocus": dz, "magnification": m}


def iris_vertices(iris: Iris) -> np.ndarray:
    k = np.arange(iris.n)
    a = iris.rotation + 2 * math.pi * k / iris.n
    return iris.circumradius * np.stack([np.cos(a), np.sin(a)], axis=-1)


def inside_iris(iris: Iris, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Point-in-shape test: inside the polygon, or inside one of the circular caps that
    the outward arcs add beyond the chords (a concave arc removes its cap instead)."""
    v = iris_vertices(iris)
    inside = np.ones(np.broadcast(x, y).shape, bool)
    caps = np.zeros_like(inside)
    cut = np.zeros_like(inside)
    c = iris.curvature
    for k in range(iris.n):
        p, q = v[k], v[(k + 1) % iris.n]
        d = q - p
        # left of the edge p→q is inside (vertices counter-clockwise)
        side = d[0] * (y - p[1]) - d[1] * (x - p[0])
        inside &= side >= 0
        if c != 0.0:
            rho = iris.circumradius / abs(c)
            half = 0.5 * math.hypot(*d)
            mid = 0.5 * (p + q)
            nrm = np.array([d[1], -d[0]]) / math.hypot(*d)  # outward normal
            h = math.sqrt(rho * rho - half * half)
            # centre of the arc's circle: behind the chord for an outward bulge
            centre = mid - np.sign(c) * h * nrm
            in_circle = (x - centre[0]) ** 2 + (y - centre[1]) ** 2 <= rho * rho
            beyond = side < 0
            if c > 0:
                caps |= in_circle & beyond
            else:
                cut |= in_circle & ~beyond
    return (inside & ~cut) | caps


def iris_area(iris: Iris) -> float:
    """Analytic area: the polygon plus (or minus) the n circular segments."""
    v = iris_vertices(iris)
    x, y = v[:, 0], v[:, 1]
    poly = 0.5 * abs(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))
    if iris.curvature == 0:
        return poly
    chord = np.hypot(*(v[1] - v[0]))
    rho = iris.circumradius / abs(iris.curvature)
    alpha = math.asin(chord / (2 * rho))
    seg = 0.5 * rho * rho * (2 * alpha - math.sin(2 * alpha))
    return poly + math.copysign(iris.n * seg, iris.curvature)


# ----------------------------------------------------------------------- the field

def pupil_function(iris: Iris, *, wavelength: float, z_r: float, z_i: float,
                   spacing: float, size: int, supersample: int) -> tuple[np.ndarray, float]:
    """Cell means of P·exp(ikW) on a ``size``² grid of cell ``spacing`` (centred on the
    axis at index size//2), by ``supersample``² point tests per cell; and the pupil's
    power in cells, Σ of the cells' mean |P|² (their covered fractions)."""
    k = 2 * math.pi / wavelength
    half = int(math.ceil(iris.circumradius * 1.01 / spacing)) + 2
    idx = np.arange(-half, half + 1)
    sub = (np.arange(supersample) + 0.5) / supersample - 0.5
    # fine coordinates: cell i, sub-point s → (i + s)·spacing
    fine = (idx[:, None] + sub[None, :]).ravel() * spacing
    xx, yy = np.meshgrid(fine, -fine)  # row index grows downwards, y up
    inside = inside_iris(iris, xx, yy)
    r2 = xx * xx + yy * yy
    w_dz = 0.5 * (1.0 / z_i - 1.0 / z_r) * r2
    rho2 = r2 / iris.zernike_radius ** 2
    w_ab = iris.spherical * math.sqrt(5.0) * (6 * rho2 * rho2 - 6 * rho2 + 1)
    fieldv = np.where(inside, np.exp(1j * k * (w_dz + w_ab)), 0.0)
    m = len(idx)
    cells = fieldv.reshape(m, supersample, m, supersample).mean(axis=(1, 3))
    out = np.zeros((size, size), complex)
    c = size // 2
    out[c - half: c + half + 1, c - half: c + half + 1] = cells
    return out, float(np.count_nonzero(inside)) / supersample ** 2


def intensity(iris: Iris, *, wavelength: float, z_r: float, z_i: float,
              pixel_pitch: float, pixel_supersample: int, fft_size: int,
              pupil_supersample: int) -> np.ndarray:
    """The intensity on a sub-pixel grid of spacing pitch/s (fft_size² samples, the axis
    at index fft_size//2), each sample the fraction of the pupil's power in its cell."""
    du = pixel_pitch / pixel_supersample
    spacing = wavelength * z_r / (fft_size * du)
    p, power = pupil_function(iris, wavelength=wavelength, z_r=z_r, z_i=z_i,
                              spacing=spacing, size=fft_size, supersample=pupil_supersample)
    # kernel exp(+2πi x·ξ/(λ z_R)) = inverse DFT; axes: row index ↔ −y in both planes
    u = np.fft.fftshift(np.fft.ifft2(np.fft.ifftshift(p)))
    # each cell holds the mean of s² point values, s a side: a sum of s shifted copies
    # of the pupil per axis, whose transform multiplies the field by the Dirichlet
    # kernel D(x) = sin(πx/L) / (s sin(πx/(sL))) (L = N du the period); divided out on
    # the principal period (x = k du, |k| ≤ N/2), else a defocused blur dims towards
    # its edge by about (πx/L)²/3 (2 % of the peak at x = L/13)
    s = pupil_supersample
    t = np.pi * (np.arange(fft_size) - fft_size // 2) / fft_size  # π x / L
    d = np.ones(fft_size)
    nz = t != 0
    d[nz] = np.sin(t[nz]) / (s * np.sin(t[nz] / s))
    u = u / (d[:, None] * d[None, :])
    # U(x) = a N² u with a the cell's area, and a du² = (λ z_R)²/N²: the power through a
    # sample's area du² is |U|² du²/(λ z_R)², its fraction of the pupil's a·power is
    return np.abs(u) ** 2 * (fft_size * fft_size) / power


def disc_image(radius: float, shape, centre_rc, *, spacing: float, supersample: int = 4
               ) -> np.ndarray:
    """Coverage (0…1) of each cell of a grid of ``spacing`` by a disc of ``radius``
    (metres on the sensor) centred at ``centre_rc`` (sample units), by point tests."""
    h, w = shape
    sub = (np.arange(supersample) + 0.5) / supersample - 0.5
    r0, c0 = centre_rc
    rr = (np.arange(h)[:, None] + sub[None, :]).ravel() - r0
    cc = (np.arange(w)[:, None] + sub[None, :]).ravel() - c0
    inside = (rr[:, None] ** 2 + cc[None, :] ** 2) * spacing ** 2 <= radius ** 2
    cov = inside.reshape(h, supersample, w, supersample).mean(axis=(1, 3))
    if not cov.any():
        raise ValueError(f"the source's image (radius {radius:.3g} m) is smaller than a "
                         f"sample ({spacing:.3g} m); use a finer pixel_supersample")
    return cov


def channel_image(camp: Campaign, cfg: Configuration, channel: int) -> np.ndarray:
    """The power reaching each of the frame's pixels for one colour channel, from a disc
    of unit radiance: irradiance A/z_R² over the disc's geometric image, spread by the
    intensity, integrated over each pixel (so the total is A·π r_s²/d² whatever the
    focus, d the source's distance from the pupil, as it must be).""" 
    g = lens_geometry(camp.lens, cfg.focus_distance, cfg.object_distance)
    s, n = camp.pixel_supersample, camp.fft_size
    sen = camp.sensor
    inten = intensity(camp.iris, wavelength=sen.wavelengths[channel], z_r=g["z_R"],
                      z_i=g["z_i"], pixel_pitch=sen.pixel_pitch, pixel_supersample=s,
                      fft_size=n, pupil_supersample=camp.pupil_supersample)
    h, w = camp.frame
    # place the source: frame pixel (r, c) spans sub-samples [r·s, (r+1)·s); its centre
    # (integer r) sits at sub-sample coordinate r·s + (s − 1)/2
    r0, c0 = cfg.source_position
    rs = r0 * s + (s - 1) / 2
    cs = c0 * s + (s - 1) / 2
    radius = abs(g["magnification"]) * camp.source_radius
    disc = disc_image(radius, (n, n), (n // 2 + (rs - int(rs)), n // 2 + (cs - int(cs))),
                      spacing=sen.pixel_pitch / s)
    # a circular convolution with the intensity moved to index 0 keeps the disc's centre
    # (n//2 + frac); a roll of whole samples then puts it at (rs, cs)
    img = np.real(np.fft.ifft2(np.fft.fft2(disc) * np.fft.fft2(np.fft.ifftshift(inten))))
    img = np.roll(img, (int(rs) - n // 2, int(cs) - n // 2), axis=(0, 1))
    img = img[: h * s, : w * s]
    pix = img.reshape(h, s, w, s).sum(axis=(1, 3))
    # irradiance L·A/z_R² (L = 1) over the disc's image, times each sample's area
    return pix * iris_area(camp.iris) / g["z_R"] ** 2 * (sen.pixel_pitch / s) ** 2


def cfa_channel(pattern: str, shape) -> np.ndarray:
    """Channel index (0 R, 1 G, 2 B) of each pixel for a 2×2 Bayer ``pattern``."""
    tile = np.array([CHANNELS.index(ch) for ch in pattern]).reshape(2, 2)
    h, w = shape
    return np.tile(tile, (h // 2 + 1, w // 2 + 1))[:h, :w]


def make_captures(camp: Campaign, *, seed: int = 0, noise: bool = True
                  ) -> tuple[list[dict], dict]:
    """Every capture of the campaign: dicts with ``name``, ``configuration``,
    ``exposure_time``, ``raw`` (uint16 mosaic in DN); and the truth (SI units).
    ``noise=False``: the expected photo-electrons, no read noise (still quantised and
    clipped): a fit to these measures the models' difference, not the noise's."""
    rng = np.random.default_rng(seed)
    sen = camp.sensor
    chan = cfa_channel(sen.pattern, camp.frame)
    caps = []
    truth = {"defocus": {}, "magnification": {}}
    for cfg in camp.configurations:
        g = lens_geometry(camp.lens, cfg.focus_distance, cfg.object_distance)
        truth["defocus"][cfg.name] = g["defocus"]
        truth["magnification"][cfg.name] = g["magnification"]
        planes = np.stack([channel_image(camp, cfg, c) for c in range(3)])
        mosaic = np.take_along_axis(planes, chan[None], axis=0)[0]
        q = np.asarray(sen.quantum_scale)[chan]
        for t in cfg.exposure_times:
            expected = np.maximum(mosaic * q * t, 0.0)
            electrons = rng.poisson(expected) if noise else expected
            read = rng.normal(0.0, sen.read_noise_dn, mosaic.shape) if noise else 0.0
            dn = sen.black_level + electrons / sen.gain_e_per_dn + read
            raw = np.clip(np.round(dn), 0, sen.white_level).astype(np.uint16)
            tag = f"{t:.4g}".replace(".", "p")
            caps.append({"name": f"{cfg.name}_t{tag}s", "configuration": cfg.name,
                         "exposure_time": float(t), "raw": raw})
    i = camp.iris
    truth.update(circumradius=i.circumradius, rotation=i.rotation, curvature=i.curvature,
                 spherical=i.spherical, source_radius=camp.source_radius,
                 area=iris_area(i))
    return caps, truth


# ---------------------------------------------------------------------- a campaign

#: the campaign of ``fit/curved-iris-raw``: a 50 mm lens at about f/11 with a 9-blade
#: curved iris and spherical aberration, a small disc at 1.5 m photographed focused on it,
#: focused nearer (sensor behind focus) and farther (sensor in front), 3 exposures each
CURVED_IRIS = Campaign(
    frame=(128, 128),
    configurations=(
        Configuration("focused", 1.5, 1.5, (), (64.3, 63.6)),
        Configuration("near", 1.2, 1.5, (), (63.8, 64.4)),
        Configuration("far", 2.2, 1.5, (), (64.45, 63.7)),
    ),
)


def bracket(camp: Campaign, cfg: Configuration, *, steps=(0.25, 1.0, 4.0),
            peak_fraction: float = 0.5) -> tuple:
    """Exposure times (rounded to 3 figures) that put the brightest pixel of the middle
    exposure at ``peak_fraction`` of the full scale."""
    sen = camp.sensor
    peak = max(np.max(channel_image(camp, cfg, c)) * sen.quantum_scale[c] for c in range(3))
    full = (sen.white_level - sen.black_level) * sen.gain_e_per_dn
    t_mid = peak_fraction * full / peak
    return tuple(float(f"{t_mid * s:.3g}") for s in steps)


def write_campaign(out, camp: Campaign = CURVED_IRIS, *, seed: int = 0, roi=(96, 96),
                   noise: bool = True) -> None:
    """Write the captures (DNG, via difstar.io.write_dng: files only) and a RAW-fit
    manifest with the truth to the new folder ``out``."""
    import dataclasses
    import json
    from pathlib import Path

    from difstar.io import write_dng

    out = Path(out)
    (out / "captures").mkdir(parents=True)
    cfgs = tuple(dataclasses.replace(c, exposure_times=bracket(camp, c))
                 for c in camp.configurations)
    camp = dataclasses.replace(camp, configurations=cfgs)
    caps, truth = make_captures(camp, seed=seed, noise=noise)
    sen, lens, iris = camp.sensor, camp.lens, camp.iris
    entries = []
    by_cfg = {c.name: c for c in cfgs}
    for cp in caps:
        f = f"captures/{cp['name']}.dng"
        write_dng(out / f, cp["raw"], pattern=sen.pattern, black_level=sen.black_level,
                  white_level=sen.white_level, exposure_time=cp["exposure_time"],
                  focal_length=lens.focal_length, camera_model="independent NumPy camera")
        r, c = by_cfg[cp["configuration"]].source_position
        entries.append({"file": f, "name": cp["name"], "configuration": cp["configuration"],
                        "exposure_time": cp["exposure_time"],
                        "source_position": [round(r), round(c)]})
    offsets = {c.name: [c.source_position[0] - round(c.source_position[0]),
                        c.source_position[1] - round(c.source_position[1])] for c in cfgs}
    dz = truth["defocus"]
    params = {
        "circumradius": {"free": True, "start": iris.circumradius, "bounds": [1.5e-3, 3.0e-3]},
        "curvature": {"free": True, "start": iris.curvature, "bounds": [-0.2, 1.0],
                      "perturb_scale": 0.1},
        "rotation": {"free": True, "start": iris.rotation, "bounds": [-0.3, 0.5]},
        "z11": {"free": True, "start": iris.spherical * 1e9, "bounds": [-400.0, 400.0],
                "perturb_scale": 50.0},
        "source_radius": {"free": True, "start": camp.source_radius,
                          "bounds": [0.05e-3, 0.6e-3]},
        "phi0": {"free": True, "start": [1.0, 1.0, 1.0], "bounds": [1e-4, 1e4]},
        # RAW data are linear up to the clip: the response curves held there
        "toe": {"free": False, "start": [0.0] * 3},
        "knee": {"free": False, "start": [1000.0] * 3},
        "background": {"free": True, "start": [0.0] * 3, "bounds": [-1e-4, 2e-4],
                       "perturb_scale": 2e-5},
    }
    for c in cfgs:
        d = dz[c.name] if abs(dz[c.name]) > 1e-12 else 0.0
        params[f"defocus/{c.name}"] = (
            {"free": True, "start": d, "bounds": sorted([0.5 * d, 1.5 * d])} if abs(d) > 1e-9
            else {"free": True, "start": 0.0, "bounds": [-1e-3, 1e-3], "perturb_scale": 2e-4})
        params[f"source_offset/{c.name}"] = {"free": True, "start": [0.0, 0.0],
                                             "bounds": [-3, 3], "perturb_scale": 2}
    values = {"circumradius": iris.circumradius, "curvature": iris.curvature,
              "rotation": iris.rotation, "z11": iris.spherical * 1e9,
              "source_radius": camp.source_radius}
    values |= {f"defocus/{k}": v if abs(v) > 1e-12 else 0.0 for k, v in dz.items()}
    values |= {f"source_offset/{k}": v for k, v in offsets.items()}
    manifest = {
        "name": "curved-iris-raw",
        "description": (
            "RAW brackets of a 9-blade curved iris (curvature 0.5) with spherical aberration "
            "(Z11 = 100 nm RMS) through a 50 mm lens at about f/11, a 0.25 mm disc at 1.5 m, "
            "focused on it, nearer and farther; made by tests/raw_generator.py, a NumPy "
            "camera independent of difstar's model (its own pupil sampling, pixel "
            "integration, linear sensor with clipping, GBRG layout and noise)."),
        "camera": {"focal_length": lens.focal_length,
                   "principal_separation": lens.principal_separation,
                   "pupil_magnification": lens.pupil_magnification,
                   "pixel_pitch": sen.pixel_pitch, "wavelengths": list(sen.wavelengths),
                   "blades": iris.n, "zernike_radius": iris.zernike_radius},
        "noise": {"gain_e_per_dn": sen.gain_e_per_dn, "read_noise_dn": sen.read_noise_dn},
        "configurations": [{"name": c.name, "focus_distance": c.focus_distance,
                            "object_distance": c.object_distance} for c in cfgs],
        "roi_size": list(roi),
        "captures": entries,
        "parameters": params,
        "grid": {"accuracy": 0.01},
        "solver": {"method": "lm", "max_steps": 60, "rtol": 1e-6, "atol": 1e-6, "ftol": 1e-7,
                   "reweight": 1},
        "truth": {"made_by": f"tests/raw_generator.py (CURVED_IRIS, seed {seed})",
                  "values": values},
    }
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(description="write the curved-iris RAW campaign")
    ap.add_argument("--out", required=True, help="a new folder")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--noiseless", action="store_true",
                    help="expected signal, no photon or read noise (a fit then measures "
                         "the models' difference)")
    a = ap.parse_args()
    write_campaign(a.out, seed=a.seed, noise=not a.noiseless)
