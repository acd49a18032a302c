"""The normal equations of a least-squares fit's Jacobian, and the Jacobian's block
structure that makes them cheap: where residuals fall into blocks (the stars of a field)
and a parameter moves one block's alone, the columns share compressed directions
(:func:`column_colours`, used by :func:`difstar._lm.with_batched_jacobian`), and JᵀJ
comes from the Jacobian along those directions only (:func:`normal_equations`), for the
solver's damped steps (:class:`NormalDescent`) and the covariance
(:func:`normal_covariance_of`)."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx


def column_colours(owners) -> np.ndarray:
    """Which compressed direction each Jacobian column is computed in (``owners``: a
    sequence of ints, one per column): a column whose
    ``owners`` entry is −1 (a shared parameter: it moves every residual) has one of its
    own; the k-th column owned by block c (a parameter of block c alone: a star's
    centre moves its own window's residuals, no other's) shares the k-th direction after
    the shared ones with every other block's k-th column (Curtis, Powell and Reid's
    compression: columns with disjoint rows, summed into one direction and told apart
    by their rows). P columns of S shared and k per block over B blocks: S + k directions
    instead of S + k B."""
    owners = np.asarray(owners, int)
    colour = np.empty(len(owners), int)
    shared = owners < 0
    colour[shared] = np.arange(int(shared.sum()))
    rank: dict[int, int] = {}
    for j in np.flatnonzero(~shared):
        colour[j] = int(shared.sum()) + rank.get(int(owners[j]), 0)
        rank[int(owners[j])] = rank.get(int(owners[j]), 0) + 1
    return colour


@dataclasses.dataclass(frozen=True)
class BlockColumns:
    """A Jacobian's block structure (hashable: a static part of the solver): its rows,
    a flat vector, fall into ``blocks`` contiguous blocks of ``size`` rows each (the
    stars of a field, in order), and each column is shared (``owner`` −1: it moves
    every block's rows) or one block's own (``owner`` that block: it moves no other's);
    ``colour``: the compressed direction each column is computed in
    (:func:`column_colours`)."""

    colour: tuple[int, ...]
    owner: tuple[int, ...]
    blocks: int
    size: int

    @classmethod
    def of(cls, blocks) -> BlockColumns | None:
        """From :func:`with_batched_jacobian`'s ``blocks`` = (owners, rows): None unless
        the rows are one flat vector of equal contiguous blocks, each column's owner
        among them."""
        if blocks is None:
            return None
        owners, rows = blocks
        if isinstance(rows, (list, tuple)):  # a row array per output: not one vector
            return None
        found = equal_blocks(rows)
        if found is None:
            return None
        n_blocks, size = found
        owners = np.asarray(owners, int)
        if np.any(owners >= n_blocks):
            return None
        return cls(tuple(int(c) for c in column_colours(owners)),
                   tuple(int(o) for o in owners), n_blocks, size)


def equal_blocks(rows) -> tuple[int, int] | None:
    """(blocks, size) where ``rows`` (each residual's block) is one flat vector of equal
    contiguous blocks 0, 1, …, in order; else None."""
    rows = np.asarray(rows)
    if rows.ndim != 1 or rows.size == 0:
        return None
    n_blocks = int(rows.max()) + 1
    if rows.size % n_blocks or not np.array_equal(
            rows, np.repeat(np.arange(n_blocks), rows.size // n_blocks)):
        return None
    return n_blocks, rows.size // n_blocks


def normal_equations(info, structure: BlockColumns | None = None):
    """(JᵀJ, Jᵀr) of a solver's linearisation ``info`` (optimistix's ``ResidualJac``:
    its Jacobian an operator, its residuals a pytree, flattened in tree order). Dense:
    J materialised, pixels × P² operations. With ``structure``: J applied to the G
    compressed directions only (each the sum of its columns' unit vectors: G products
    of J with a vector), each block's G × G products of them, and JᵀJ's entries read
    off those (a shared column's products summed over the blocks, a block's own column
    with its own block's, two blocks' own columns 0): pixels × G² operations, however
    many blocks (for 120 stars of a field, G = 17 against P = 493)."""
    r = jnp.concatenate([jnp.ravel(x) for x in jax.tree_util.tree_leaves(info.residual)])
    if structure is None:
        jac = info.jac.as_matrix()
        return jac.T @ jac, jac.T @ r
    seeds = direction_seeds(structure.colour)

    def along(seed):
        out = info.jac.mv(seed)
        return jnp.concatenate([jnp.ravel(x) for x in jax.tree_util.tree_leaves(out)])

    return block_normal_equations(jax.vmap(along)(jnp.asarray(seeds, r.dtype)), r,
                                  structure)


def direction_seeds(colour, count: int | None = None) -> np.ndarray:
    """The compressed directions (G, P) of columns in directions ``colour``
    (:func:`column_colours`): each the sum of its columns' unit vectors, with zero rows
    after them up to ``count`` rows where given."""
    colour = np.asarray(colour)
    seeds = np.zeros((int(colour.max()) + 1 if count is None else count, colour.size))
    seeds[colour, np.arange(colour.size)] = 1.0
    return seeds


def block_normal_equations(jc, r, structure: BlockColumns):
    """(JᵀJ, Jᵀr) from the Jacobian along the compressed directions ``jc`` (G, rows:
    J times each of :func:`direction_seeds` of its colours) and the residuals ``r`` (rows), for a
    Jacobian of that ``structure`` (:func:`normal_equations`)."""
    colour = np.asarray(structure.colour)
    owner = np.asarray(structure.owner)
    b, n = structure.blocks, structure.size
    jc = jc.reshape(-1, b, n)
    gram = jnp.einsum("gbn,hbn->bgh", jc, jc)  # (B, G, G)
    gb = jnp.einsum("gbn,bn->bg", jc, r.reshape(b, n))  # (B, G)
    ci, cj = colour[:, None], colour[None, :]
    oi, oj = owner[:, None], owner[None, :]
    blk = np.where(oi >= 0, oi, np.where(oj >= 0, oj, 0))  # the block a pair is read in
    both_shared = (oi < 0) & (oj < 0)
    jtj = jnp.where(both_shared, gram.sum(axis=0)[ci, cj],
                    jnp.where((oi < 0) | (oj < 0) | (oi == oj), gram[blk, ci, cj], 0.0))
    g = jnp.where(owner < 0, gb.sum(axis=0)[colour], gb[np.maximum(owner, 0), colour])
    return jtj, g


def column_scale(jtj, xp, *, fill: float):
    """1 / each column's norm, read off the normal matrix ``jtj``'s diagonal (``xp``:
    ``jnp`` inside a program, ``np`` outside); ``fill`` where a column is zero (a
    parameter the residuals do not depend on): 0 leaves it out of a pseudo-inverse, 1
    keeps a damped system regular. The one column scaling of the solver's steps, its
    Gauss–Newton gain and the covariance (parameters of any units compare)."""
    norm = xp.sqrt(xp.maximum(xp.diagonal(jtj), 0.0))
    return xp.where(norm > 0, 1.0 / xp.where(norm > 0, norm, 1.0), fill)


class _NormalState(eqx.Module):
    jtj: jax.Array
    g: jax.Array


class NormalDescent(optx.AbstractDescent):
    """Levenberg–Marquardt's damped step −(JᵀJ + λI)⁻¹Jᵀr (λ = 1/step size, as
    optimistix's ``DampedNewtonDescent``) from the normal equations of a Jacobian with a
    block structure (:func:`normal_equations`): made once per accepted point, then each
    tried step size is a P × P solve, where optimistix's QR of the (pixels + P) × P
    system costs pixels × P² every try. Column-scaled for the solve (parameters of
    any units compare); λ > 0 keeps the system positive definite, and a near-singular
    one (λ tiny, a direction the data do not determine) gives a long step, which the
    trust region rejects and shortens."""

    structure: BlockColumns = eqx.field(static=True)

    def init(self, y, f_info_struct):
        p = int(np.prod(jnp.shape(y)))
        dtype = jnp.result_type(*(x.dtype for x in
                                  jax.tree_util.tree_leaves(f_info_struct.residual)))
        return _NormalState(jnp.zeros((p, p), dtype), jnp.zeros(p, dtype))

    def query(self, y, f_info, state):
        del y, state
        jtj, g = normal_equations(f_info, self.structure)
        return _NormalState(jtj, g)

    def step(self, step_size, state):
        pred = step_size > jnp.finfo(step_size.dtype).eps
        lam = jnp.where(pred, 1.0 / jnp.where(pred, step_size, 1.0),
                        jnp.finfo(step_size.dtype).max)
        jtj, g = state.jtj, state.g
        scale = column_scale(jtj, jnp, fill=1.0)
        a = jtj * scale[:, None] * scale[None, :] + jnp.diag(lam * scale * scale)
        z = jnp.linalg.solve(a, -g * scale)
        return z * scale, optx.RESULTS.successful


def normal_covariance(jac):
    """(JᵀJ)⁺ of a Jacobian ``jac`` (residuals × parameters, residuals weighted by 1/σ),
    by a pseudo-inverse of the column-scaled normal matrix (parameters of any units
    compare), and the columns' norms (0: a parameter the residuals do not depend on; its
    row and column of the covariance are 0). The one Gauss–Newton covariance of every
    difstar fit (RAW captures in the solver's unbounded coordinates, star images in
    physical ones)."""
    jac = np.asarray(jac)
    return normal_covariance_of(jac.T @ jac)


def normal_covariance_of(jtj):
    """:func:`normal_covariance` from the normal matrix JᵀJ itself (NumPy, P × P)."""
    jtj = np.asarray(jtj)
    colnorm = np.sqrt(np.maximum(np.diag(jtj), 0.0))
    dscale = column_scale(jtj, np, fill=0.0)
    cov = dscale[:, None] * np.linalg.pinv(dscale[:, None] * jtj * dscale[None, :],
                                           rcond=1e-12) * dscale[None, :]
    return cov, colnorm
