"""The response curve: monotone, 0 at 0, saturating at 1, linear in the middle, and
differentiable everywhere (at E = 0 and deep in saturation)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from difstar._sensor import Response, response_curve, sensor


def test_limits_and_monotonicity():
    e = jnp.linspace(0.0, 5.0, 2001)
    for toe, knee in [(0.0, 60.0), (0.05, 20.0), (0.2, 5.0)]:
        z = response_curve(e, toe, knee)
        assert float(z[0]) == 0.0
        d = np.diff(np.asarray(z))
        assert np.all(d >= 0)  # monotone; strictly so below the knee (float64 rounds above)
        assert np.all(d[np.asarray(e)[1:] < 0.9] > 0)
        assert float(response_curve(jnp.asarray(1e6), toe, knee)) == pytest.approx(1.0, abs=1e-9)
        assert float(jnp.max(z)) <= 1.0


def test_linear_part_and_toe_shape():
    # far above the toe and below the knee, ζ = E − e_t (a straight line of slope 1)
    toe, knee = 0.02, 200.0
    e = jnp.asarray([0.3, 0.5, 0.7])
    z = response_curve(e, toe, knee)
    lin = np.sqrt(np.asarray(e) ** 2 + toe**2) - toe
    np.testing.assert_allclose(z, lin, atol=1e-9)
    # in the toe the curve is quadratic: ζ ≈ E² / (2 e_t) (a Taylor expansion)
    assert float(response_curve(jnp.asarray(1e-3), toe, knee)) == pytest.approx(1e-6 / 0.04, rel=1e-2)


@pytest.mark.parametrize("e0", [0.0, 0.5, 1.0, 30.0])
def test_gradients_finite_and_match_fd(e0):
    # E = 0 and deep saturation (E = 30) are hard points
    def f(e, toe, knee):
        return response_curve(e, toe, knee)

    for toe in (0.0, 0.03):
        g = jax.grad(f, argnums=(0, 1, 2))(jnp.asarray(e0), jnp.asarray(toe), jnp.asarray(20.0))
        assert all(np.isfinite(float(x)) for x in g)
        if e0 > 0 and toe > 0:
            eps = 1e-6
            fd = (f(e0 + eps, toe, 20.0) - f(e0 - eps, toe, 20.0)) / (2 * eps)
            assert float(g[0]) == pytest.approx(float(fd), rel=1e-6, abs=1e-12)
            fd = (f(e0, toe + eps, 20.0) - f(e0, toe - eps, 20.0)) / (2 * eps)
            assert float(g[1]) == pytest.approx(float(fd), rel=1e-6, abs=1e-12)
            h = 1e-3  # the knee enters smoothly; a larger step keeps rounding out of the FD
            fd = (f(e0, toe, 20.0 + h) - f(e0, toe, 20.0 - h)) / (2 * h)
            assert float(g[2]) == pytest.approx(float(fd), rel=1e-5, abs=1e-12)


def test_sensor_phi0_gradient_and_jit():
    img = jnp.linspace(0, 2, 3 * 4 * 5).reshape(3, 4, 5)
    resp = Response(toe=0.01, knee=30.0)

    def f(phi0):
        return jnp.sum(sensor(img, exposure_time=2.0, phi0=phi0, response=resp) ** 2)

    phi0 = jnp.asarray([1.0, 2.0, 4.0])
    g = jax.grad(f)(phi0)
    eps = 1e-6
    for c in range(3):
        d = jnp.zeros(3).at[c].set(eps)
        fd = (f(phi0 + d) - f(phi0 - d)) / (2 * eps)
        assert float(g[c]) == pytest.approx(float(fd), rel=1e-6)
    assert float(jax.jit(f)(phi0)) == pytest.approx(float(f(phi0)), rel=1e-14)
