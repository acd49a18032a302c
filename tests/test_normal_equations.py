"""Tests of difstar._normal_equations: the compressed directions of a block-structured
Jacobian, the normal equations read off them, and the Gauss–Newton covariance, against
NumPy's dense products and inverses, in float64."""

import types

import jax.numpy as jnp
import lineax as lx
import numpy as np

from difstar._normal_equations import (
    BlockColumns,
    column_colours,
    normal_covariance,
    normal_equations,
)


def test_column_colours_share_directions_between_blocks_only():
    colour = column_colours([-1, 0, 0, 1, -1, 1, 2, 2])
    assert colour.tolist() == [0, 2, 3, 2, 1, 3, 2, 3]


def test_normal_covariance_is_the_inverse_normal_matrix():
    """For a Jacobian of full rank whose columns differ by 10 decades (parameters in
    metres beside parameters in nanometres), the covariance is (JᵀJ)⁻¹ (NumPy's inverse,
    in float64); a column of zeros (a parameter nothing depends on) gets a zero row and
    column and a zero norm, and leaves the others' covariance as without it."""
    rng = np.random.default_rng(3)
    j = rng.normal(size=(200, 4)) * np.array([1e-5, 1.0, 3e4, 1e5])
    cov, norms = normal_covariance(j)
    np.testing.assert_allclose(cov, np.linalg.inv(j.T @ j), rtol=1e-9)
    np.testing.assert_allclose(norms, np.linalg.norm(j, axis=0), rtol=1e-12)
    j0 = np.insert(j, 2, 0.0, axis=1)
    cov0, norms0 = normal_covariance(j0)
    assert norms0[2] == 0 and not cov0[2].any() and not cov0[:, 2].any()
    np.testing.assert_allclose(np.delete(np.delete(cov0, 2, 0), 2, 1), cov, rtol=1e-9)


def test_block_normal_equations_equal_the_dense_ones():
    """:func:`normal_equations` with a block structure (the Jacobian applied to its 4
    compressed directions, JᵀJ read off each block's products) against JᵀJ and Jᵀr of
    the dense Jacobian (NumPy's products), to 1e-12; a Jacobian that breaks the
    structure gives other ones (the test can fail); rows that are not one vector of
    equal contiguous blocks give no structure."""
    owners = [-1, -1, 0, 0, 1, 1, 2, 2]
    rows = np.repeat(np.arange(3), 5)
    structure = BlockColumns.of((owners, rows))
    assert structure is not None and structure.blocks == 3 and structure.size == 5
    assert max(structure.colour) + 1 == 4
    # not a flat vector of equal contiguous blocks: no structure
    assert BlockColumns.of((owners, np.array([0, 1, 0, 1, 2, 2]))) is None
    assert BlockColumns.of((owners, (rows, [0, 1, 2]))) is None
    rng = np.random.default_rng(3)
    jac = np.zeros((15, 8))
    for c in range(3):
        jac[5 * c:5 * c + 5, :2] = rng.normal(size=(5, 2))
        jac[5 * c:5 * c + 5, 2 + 2 * c:4 + 2 * c] = rng.normal(size=(5, 2))
    r = rng.normal(size=15)

    def info(j):
        return types.SimpleNamespace(jac=lx.MatrixLinearOperator(jnp.asarray(j)),
                                     residual=jnp.asarray(r))

    jtj, g = normal_equations(info(jac), structure)
    np.testing.assert_allclose(jtj, jac.T @ jac, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(g, jac.T @ r, rtol=1e-12, atol=1e-12)
    dense = normal_equations(info(jac))
    np.testing.assert_allclose(dense[0], jac.T @ jac, rtol=1e-12, atol=1e-12)
    bad = jac.copy()
    bad[:5, 4] = 1.0  # block 1's own column moving block 0
    assert not np.allclose(normal_equations(info(bad), structure)[0], bad.T @ bad)
