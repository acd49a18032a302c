"""Colour rendering vs colour-science (sRGB curve, XYZ→sRGB matrix) and
colour-demosaicing (the full render chain)."""

import hashlib
import inspect
from pathlib import Path

import colour
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from colour_demosaicing import demosaicing_CFA_Bayer_Malvar2004, masks_CFA_Bayer

import difstar
from difstar._colour import camera_to_srgb, render_srgb, srgb_encode, xyz_to_srgb_linear_matrix

from difstar._sampling import choose_grid

from helpers import fd_grad


def test_srgb_encode_matches_colour():
    x = np.concatenate([np.linspace(-0.1, 1.1, 241), [0.0, 0.0031308, 0.00313, 0.0031309, 1.0],
                        np.geomspace(1e-8, 1, 50)])
    ref = colour.models.eotf_inverse_sRGB(np.clip(x, 0, 1))
    np.testing.assert_allclose(srgb_encode(jnp.asarray(x)), ref, rtol=0, atol=1e-14)  # float64
    ref2 = colour.cctf_encoding(np.clip(x, 0, 1), function="sRGB")
    np.testing.assert_allclose(srgb_encode(jnp.asarray(x)), ref2, rtol=0, atol=1e-14)


def test_srgb_encode_grad():
    g = jax.jit(jax.grad(srgb_encode))
    # exactly at the clip limits: finite, the one-sided derivative from inside
    assert np.isfinite(g(0.0)) and np.isfinite(g(1.0))
    np.testing.assert_allclose(g(0.0), 12.92, rtol=1e-14)
    np.testing.assert_allclose(g(1.0), 1.055 / 2.4, rtol=1e-14)
    assert g(-0.5) == 0.0 and g(1.5) == 0.0  # clipped
    # finite differences away from the kink at 0.0031308 (step 1e-6 relative, central)
    enc = jax.jit(srgb_encode)
    f = lambda x: float(enc(jnp.asarray(x)))  # noqa: E731
    for x in [1e-4, 0.002, 0.01, 0.2, 0.5, 0.9]:
        np.testing.assert_allclose(g(x), fd_grad(f, x, 1e-6 * x), rtol=1e-6)
    # a whole image with zeros and saturated pixels: no NaN in the gradient
    img = jnp.asarray(np.random.default_rng(0).uniform(-0.2, 1.2, (3, 8, 8))).at[:, 0, 0].set(0.0)
    gi = jax.jit(jax.grad(lambda a: jnp.sum(srgb_encode(a))))(img)
    assert np.all(np.isfinite(gi))


def test_srgb_encode_jit():
    x = jnp.linspace(-0.1, 1.1, 101)
    np.testing.assert_allclose(jax.jit(srgb_encode)(x), srgb_encode(x), rtol=0, atol=1e-15)


def test_xyz_matrix_is_colours():
    m = xyz_to_srgb_linear_matrix()
    np.testing.assert_array_equal(m, colour.RGB_COLOURSPACES["sRGB"].matrix_XYZ_to_RGB)
    # D65 white (Y = 1) → linear sRGB (1, 1, 1) within the standard's 4-digit rounding
    white = colour.xy_to_XYZ(colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"])
    np.testing.assert_allclose(m @ white, 1.0, atol=1e-3)


def test_camera_to_srgb():
    rgb = np.random.default_rng(1).random((3, 6, 7))
    m = np.random.default_rng(2).normal(size=(3, 3))
    np.testing.assert_allclose(camera_to_srgb(jnp.asarray(rgb), jnp.asarray(m)),
                               np.einsum("ij,jhw->ihw", m, rgb), rtol=0, atol=1e-14)
    with pytest.raises(ValueError, match=r"matrix must have shape \(3, 3\)"):
        inspect.unwrap(camera_to_srgb)(jnp.asarray(rgb), jnp.eye(4))


def _render_reference(cfa, pattern, gains, matrix, highlight="clip"):
    masks = np.stack(masks_CFA_Bayer(cfa.shape, pattern))
    balanced = cfa * np.tensordot(gains, masks, axes=1)
    rgb = demosaicing_CFA_Bayer_Malvar2004(balanced, pattern)  # (h, w, 3)
    if highlight == "clip":  # dcraw's default: nothing above the least-gained channel's white
        rgb = np.minimum(rgb, gains.min())
    srgb_lin = np.clip(rgb @ matrix.T, 0, 1)
    return np.moveaxis(colour.cctf_encoding(srgb_lin, function="sRGB"), -1, 0)


@pytest.mark.parametrize("pattern", ["RGGB", "GBRG"])
def test_render_srgb_matches_reference_chain(pattern):
    rng = np.random.default_rng(3)
    cfa = rng.random((32, 48)) * 0.6
    cfa[5:9, 10:16] = 1.0  # saturated patch
    gains = np.array([2.0, 1.0, 1.6])
    matrix = np.array([[1.6, -0.5, -0.1], [-0.2, 1.5, -0.3], [0.0, -0.4, 1.4]])
    out = render_srgb(jnp.asarray(cfa), pattern, white_balance=jnp.asarray(gains),
                      matrix=jnp.asarray(matrix))
    assert out.shape == (3, 32, 48)
    assert float(out.min()) >= 0.0 and float(out.max()) <= 1.0
    ref = _render_reference(cfa, pattern, gains, matrix)
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-12)  # float64 round-off only
    # the saturated patch's interior renders neutral (rows of this matrix sum to 1)
    np.testing.assert_allclose(out[:, 6:8, 12:14], 1.0, atol=1e-12)
    none = render_srgb(jnp.asarray(cfa), pattern, white_balance=jnp.asarray(gains),
                       matrix=jnp.asarray(matrix), highlight="none")
    np.testing.assert_allclose(none, _render_reference(cfa, pattern, gains, matrix, "none"),
                               rtol=0, atol=1e-12)
    assert np.ptp(np.asarray(none)[:, 7, 13]) > 0.1  # without the clip: a colour cast
    # identity matrix: the clip changes nothing (min gain 1: the final clip does the same)
    eye = dict(white_balance=jnp.asarray(gains), matrix=jnp.eye(3))
    np.testing.assert_array_equal(render_srgb(jnp.asarray(cfa), pattern, **eye),
                                  render_srgb(jnp.asarray(cfa), pattern, highlight="none", **eye))
    with pytest.raises(ValueError, match="highlight must be"):
        render_srgb(jnp.asarray(cfa), pattern, highlight="blend", **eye)


def test_render_srgb_jit_and_grad():
    rng = np.random.default_rng(4)
    cfa = jnp.asarray(rng.random((16, 20)) * 0.5).at[3, 3].set(0.0).at[8, 8].set(1.0)
    gains = jnp.array([2.0, 1.0, 1.6])
    matrix = jnp.eye(3)
    f = lambda c, g, m: render_srgb(c, "RGGB", white_balance=g, matrix=m,  # noqa: E731
                                    demosaic_method="bilinear")
    np.testing.assert_allclose(jax.jit(f)(cfa, gains, matrix), f(cfa, gains, matrix),
                               rtol=0, atol=1e-14)
    grads = jax.jit(jax.grad(lambda c, g, m: jnp.sum(f(c, g, m)), argnums=(0, 1, 2)))(
        cfa, gains, matrix)
    for gr in grads:
        assert np.all(np.isfinite(gr))


def test_render_srgb_bad_method():
    with pytest.raises(ValueError, match="method must be one of"):
        render_srgb(jnp.zeros((4, 4)), "RGGB", white_balance=jnp.ones(3), matrix=jnp.eye(3),
                    demosaic_method="vng")


# --- natural colour from measured sensitivities ------------------------------------------

SHARED_SENS = Path(__file__).resolve().parents[1].parent / "shared/data/raw/spectral_sensitivity"


def _shared(name):
    path = SHARED_SENS / name
    if not path.is_file():  # fail loudly, never skip
        raise FileNotFoundError(
            f"measured sensitivity file missing: {path} (expected ../shared/data/raw/"
            "spectral_sensitivity/ beside the repository; see shared/data/raw/README.md)")
    return path


def test_shipped_d7000_is_the_measured_file():
    from difstar._examples import PAPER_SENSITIVITY_FILE

    shipped = PAPER_SENSITIVITY_FILE.read_bytes()
    assert shipped == _shared("Nikon_D7000_380_780_5.json").read_bytes()
    assert hashlib.sha256(shipped).hexdigest() == (
        "4002530a868b45d11ddc2e11b8db144ae2011efdda04d25ff10a2f006494ed95")  # README's
    assert (PAPER_SENSITIVITY_FILE.parent / "LICENSE-Apache-2.0.txt").is_file()
    assert '"license"                : "Apache-2.0"' in shipped.decode()


def test_paper_colour_matrix_recomputed_from_measured_file():
    from difstar._examples import PAPER_COLOUR_MATRIX, PAPER_ILLUMINANT_K, paper_sensitivities
    from difstar.io._sensitivity import (
        camera_to_srgb_matrix_from_sensitivities,
        load_spectral_sensitivity,
    )

    sens = load_spectral_sensitivity(_shared("Nikon_D7000_380_780_5.json"))
    m = camera_to_srgb_matrix_from_sensitivities(sens, illuminant=PAPER_ILLUMINANT_K)
    # the same fit: colour.matrix_idt minimises iteratively, and inputs differing by
    # round-off move its result by ~2e-9 (seen: the SD below), so 1e-6 leaves room for
    # other machines while staying far below any visible difference (1e-3)
    np.testing.assert_allclose(m, np.asarray(PAPER_COLOUR_MATRIX), rtol=0, atol=1e-6)
    # a number is a blackbody: the same as passing colour's 5000 K SD
    bb = colour.sd_blackbody(5000, sens.shape)
    np.testing.assert_allclose(m, camera_to_srgb_matrix_from_sensitivities(sens, illuminant=bb),
                               rtol=0, atol=1e-6)
    np.testing.assert_array_equal(paper_sensitivities().values, sens.values)
    camera, _ = difstar.paper_camera("focused")
    np.testing.assert_array_equal(camera.sensor.colour_matrix, np.asarray(PAPER_COLOUR_MATRIX))
    np.testing.assert_allclose(np.sum(PAPER_COLOUR_MATRIX, axis=1), 1.0, atol=2e-4)


def _uniform_mosaic(rgb, pattern, shape=(16, 16)):
    masks = np.stack(masks_CFA_Bayer(shape, pattern)).astype(float)
    return jnp.asarray(np.tensordot(rgb, masks, axes=1))


@pytest.mark.parametrize("sensitivities", ["Nikon_D7000_380_780_5.json",
                                           "Nikon_D5300_380_780_5.json", "Nikon 5100 (NPL)"])
def test_flat_spectrum_renders_grey(sensitivities):
    """An equal-energy (flat) source, recorded through measured sensitivities (camera RGB
    = Σ S_c(λ) Δλ, by difstar's channel_weights), white-balanced with the gains of the
    same sensitivities and rendered by difstar's render_srgb with the matrix fitted to the
    same sensitivities (under illuminant E), is grey: R = G = B within 1 %."""
    from difstar._spectrum import channel_weights
    from difstar.io._sensitivity import (
        camera_to_srgb_matrix_from_sensitivities,
        load_spectral_sensitivity,
        white_balance_from_sensitivities,
    )

    if sensitivities.endswith(".json"):
        sens = load_spectral_sensitivity(_shared(sensitivities))
        spec = str(_shared(sensitivities))
    else:
        sens = colour.MSDS_CAMERA_SENSITIVITIES[sensitivities]
        spec = sensitivities
    wl = np.arange(380e-9, 781e-9, 5e-9)
    raw = channel_weights(np.ones(wl.size), spec, wl).weights.sum(axis=1)
    raw = 0.4 * raw / raw.max()  # a mid exposure, nothing saturated
    gains = white_balance_from_sensitivities(sens, illuminant="E")
    m = camera_to_srgb_matrix_from_sensitivities(sens, illuminant="E")
    for pattern in ("RGGB", "BGGR"):
        out = np.asarray(render_srgb(_uniform_mosaic(raw, pattern), pattern,
                                     white_balance=jnp.asarray(gains), matrix=jnp.asarray(m)))
        px = out[:, 8, 8]
        assert np.ptp(px) / px.mean() < 0.01, px  # R = G = B within 1 % (encoded sRGB)
        lin = colour.cctf_decoding(px, function="sRGB")
        assert np.ptp(lin) / lin.mean() < 0.01, lin
    # the identity matrix the examples used before: not grey (the reason for the matrix)
    ident = np.asarray(render_srgb(_uniform_mosaic(raw, "RGGB"), "RGGB",
                                   white_balance=jnp.ones(3), matrix=jnp.eye(3)))[:, 8, 8]
    assert np.ptp(ident) / ident.mean() > 0.1


def test_5000k_source_renders_grey_through_paper_matrix():
    """A 5000 K blackbody through the measured D7000 curves, balanced with their own 5000 K
    gains, through the paper example's stored matrix: grey within 1 %."""
    from difstar._examples import PAPER_COLOUR_MATRIX, paper_sensitivities
    from difstar._spectrum import channel_weights
    from difstar.io._sensitivity import white_balance_from_sensitivities

    wl = np.arange(380e-9, 781e-9, 5e-9)
    raw = channel_weights(5000.0, paper_sensitivities(), wl).weights.sum(axis=1)
    raw = 0.3 * raw / raw.max()
    gains = white_balance_from_sensitivities(paper_sensitivities(), illuminant=5000)
    out = np.asarray(render_srgb(_uniform_mosaic(raw, "RGGB"), "RGGB",
                                 white_balance=jnp.asarray(gains),
                                 matrix=jnp.asarray(PAPER_COLOUR_MATRIX)))[:, 8, 8]
    assert np.ptp(out) / out.mean() < 0.01, out


@pytest.mark.parametrize("config", ["focused", "defocused"])
def test_paper_example_renders_neutral(config):
    """The built-in example (white source, φ0 ∝ white balance, toe ∝ 1/white balance,
    D7000 matrix): the saturated core is white, and at 1/300 of the exposure (nothing
    saturated) the centre of the disc is grey within 1 % (linear sRGB)."""
    sim = eqx.filter_jit(difstar.simulate)
    camera, scene = difstar.paper_camera(config)
    grid = choose_grid(camera, scene, crop=(128, 128), padding=0.25)
    srgb = np.asarray(sim(camera, scene, grid).srgb)
    np.testing.assert_allclose(srgb[:, 64, 64], 1.0, atol=1e-3)  # rows sum to 1 within 2e-4
    dim = eqx.tree_at(lambda s: s.exposure_time, scene, scene.exposure_time / 300)
    pred = sim(camera, dim, grid)
    assert float(np.max(pred.zeta)) < 0.9  # nothing saturated
    lin = colour.cctf_decoding(np.asarray(pred.srgb)[:, 54:74, 54:74].mean(axis=(1, 2)),
                               function="sRGB")
    assert lin[1] > 0.2 and np.ptp(lin) / lin.mean() < 0.01, lin
