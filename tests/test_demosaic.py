"""Demosaic vs colour-demosaicing (the reference implementation), whole image including
borders, all four patterns, even and odd sizes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from colour_demosaicing import (
    demosaicing_CFA_Bayer_bilinear,
    demosaicing_CFA_Bayer_Malvar2004,
)

from difstar._cfa import PATTERNS
from difstar._demosaic import demosaic, demosaic_bilinear, demosaic_malvar2004

REFS = {"bilinear": demosaicing_CFA_Bayer_bilinear, "malvar2004": demosaicing_CFA_Bayer_Malvar2004}
FNS = {"bilinear": demosaic_bilinear, "malvar2004": demosaic_malvar2004}


@pytest.mark.parametrize("method", ["bilinear", "malvar2004"])
@pytest.mark.parametrize("pattern", PATTERNS)
@pytest.mark.parametrize("shape", [(32, 48), (33, 47)])
def test_matches_colour_demosaicing(method, pattern, shape):
    rng = np.random.default_rng(hash((method, pattern, shape)) % 2**32)
    cfa = rng.random(shape)
    cfa[10:14, 20:30] = 1.5  # a bright block: Malvar's negative taps matter at its edges
    ref = np.moveaxis(REFS[method](cfa, pattern), -1, 0)
    out = FNS[method](jnp.asarray(cfa), pattern)
    assert out.shape == (3, *shape)
    # float64 sums of ≤ 25 terms of size ≤ 1.5: round-off ~1e-15
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(demosaic(jnp.asarray(cfa), pattern, method=method), ref,
                               rtol=0, atol=1e-12)


@pytest.mark.parametrize("method", ["bilinear", "malvar2004"])
def test_constant_image_is_reproduced(method):
    cfa = jnp.full((16, 20), 0.37)
    out = demosaic(cfa, "RGGB", method=method)
    # interior only: the reflected border (as in colour-demosaicing) breaks the Bayer
    # parity within 2 pixels of the edge, so a flat field is not flat there
    np.testing.assert_allclose(out[:, 2:-2, 2:-2], 0.37, rtol=0, atol=1e-14)


@pytest.mark.parametrize("method", ["bilinear", "malvar2004"])
def test_jit_and_grad(method):
    cfa = jnp.asarray(np.random.default_rng(5).random((16, 20)))
    f = lambda x: demosaic(x, "GBRG", method=method)  # noqa: E731
    np.testing.assert_allclose(jax.jit(f)(cfa), f(cfa), rtol=0, atol=1e-15)
    g = jax.jit(jax.grad(lambda x: jnp.sum(f(x) ** 2)))(cfa)
    assert np.all(np.isfinite(g))
    # linear map: gradient of a linear functional is the adjoint; check one entry by FD
    w = jnp.asarray(np.random.default_rng(6).random((3, 16, 20)))
    lin = jax.jit(lambda x: jnp.sum(w * f(x)))
    gl = jax.jit(jax.grad(lin))(cfa)
    e = jnp.zeros_like(cfa).at[0, 3].set(1.0)
    np.testing.assert_allclose(gl[0, 3], lin(cfa + e) - lin(cfa), rtol=1e-10)  # exact (linear)


def test_bad_inputs():
    with pytest.raises(ValueError, match=r"method must be one of .*malvar2004.*got 'ahd'"):
        demosaic(jnp.zeros((4, 4)), "RGGB", method="ahd")
    with pytest.raises(ValueError, match="pattern must be one of"):
        demosaic(jnp.zeros((4, 4)), "XGGB")
    with pytest.raises(ValueError, match="at least 2×2"):
        demosaic_malvar2004(jnp.zeros((1, 4)), "RGGB")
