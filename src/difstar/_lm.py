"""Levenberg–Marquardt driven step by step from Python: the one stopping rule of every
difstar fit (RAW captures and star images).

:class:`LMStepper` compiles optimistix's solver ``init`` and ``step`` for a residual
function ``fn(u, args)`` (a pytree of arrays) once; :meth:`LMStepper.solve` runs steps
from any start ``u0`` and data ``args`` of the same shapes, reporting progress from
Python after each, and stops when optimistix's own test passes (changes of u and of the
residuals below atol + rtol·size), when the loss has fallen by less than ``ftol``
(relative) over the last three accepted steps, or after :data:`MAX_REJECTED` rejected
steps in a row once one was accepted. The residual test alone asks every one of
10⁴–10⁵ residuals to settle, and after the minimum is reached the solver can go on
rejecting ever smaller steps without it ever passing; counting only accepted steps
keeps a solve that starts by shrinking its trust region from stopping at its start.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx

from ._ahead import Ahead
from ._batch import AXIS, P
from ._normal_equations import (
    BlockColumns,
    NormalDescent,
    column_colours,
    column_scale,
    direction_seeds,
    equal_blocks,
    normal_equations,
)
from ._xla import solver_jit_options

#: Consecutive rejected steps after which a solve that has moved counts as converged:
#: the trust region has shrunk by about 2^10 and no nearby point is lower.
MAX_REJECTED = 10


#: Jacobian columns computed at a time (:func:`with_batched_jacobian`): peak memory is
#: about the forward model's plus this many copies of its grid-sized tangents.
JAC_BATCH = 4


def with_batched_jacobian(raw: Callable, *, batch: int | None = None, mesh=None,
                          has_aux: bool = False, items: int | None = None,
                          blocks: tuple | None = None) -> Callable:
    """``fn(u, args)`` equal to ``raw(u, args)`` (residuals: any pytree of arrays, ``u``
    a flat vector) whose derivative in ``u`` is computed ``batch`` (default
    :data:`JAC_BATCH`) parameter directions
    at a time: a custom JVP rule linearises ``raw`` once at ``u`` and maps its linear map
    over the rows of the identity (``lax.map``), then applies the resulting Jacobian to
    the tangent. Forward mode through the whole chain for all P directions at once (what
    optimistix's Levenberg–Marquardt and ``jax.jacfwd`` do by themselves) holds P copies
    of every grid-sized intermediate — 8 GB for the 81² Spitzer PSF's 16 parameters;
    this way the linearisation keeps the (residuals × P) matrix and ``batch`` tangents.
    ``args`` is not differentiated.

    ``items``: ``raw(u, args, i)`` gives item ``i``'s residuals (``i`` a traced index,
    0 ≤ i < ``items``), and ``fn(u, args)`` all items' stacked on a leading axis. The
    items are one ``lax.map``, each linearised inside it: one trace and one compiled
    body for all (the RAW fit's configurations on one grid), where linearising the map
    as a whole would compile its body for the primal and again for the tangents.

    ``mesh`` (a one-axis :func:`difstar._batch.device_mesh` of more than one device):
    the columns are shared out over its devices (``shard_map``): each device linearises
    at ``u`` (the forward model, a few per cent of a step, repeated on every device) and
    computes its own slice of the directions, ``batch`` at a time; the rest of a solver
    step (on a P-column matrix) is the same on every device.

    ``has_aux``: ``raw`` returns (residuals, aux), aux computed on the way (values the
    residuals were made with) and not differentiated (its tangent is zero): the same
    trace gives both (not with ``mesh``).

    ``blocks``: ``(owners, rows)``, where the residuals fall into blocks (the stars of a
    joint fit) and some parameters move one block's alone: ``owners`` (P,) the block of
    each parameter (−1: shared, it moves every block), ``rows`` a pytree like ``raw``'s
    residuals of int arrays broadcastable to each leaf, the block of each residual. The
    columns are then computed compressed (:func:`column_colours`: S + k directions for S
    shared parameters and k per block, however many blocks) and told apart by their
    rows. The caller vouches for the structure: a parameter of block c must not move a
    residual of another block (not with ``items`` or ``mesh``)."""
    if has_aux and mesh is not None:
        raise ValueError("with_batched_jacobian: has_aux is not supported with a mesh")
    if blocks is not None and (items is not None or mesh is not None):
        raise ValueError("with_batched_jacobian: blocks is not supported with items or a "
                         "mesh")
    batch = JAC_BATCH if batch is None else int(batch)
    n_dev = 1 if mesh is None else int(mesh.size)

    def each(fun):  # fun(i) for every item, stacked (the function itself without items)
        return fun(None) if items is None else jax.lax.map(fun, jnp.arange(items))

    def at(u, args, i):
        return raw(u, args) if items is None else raw(u, args, i)

    @jax.custom_jvp
    def fn(u, args):
        return each(lambda i: at(u, args, i))

    @fn.defjvp
    def _fn_jvp(primals, tangents):
        u, args = primals
        du = tangents[0]  # the data are not differentiated
        n = u.shape[0]
        if n == 0:
            y = each(lambda i: at(u, args, i))
            return y, jax.tree_util.tree_map(jnp.zeros_like, y)
        colour = None
        if blocks is not None:
            owners = np.asarray(blocks[0], int)
            if owners.shape != (n,):
                raise ValueError(f"with_batched_jacobian: blocks' owners has "
                                 f"{owners.size} entries for {n} parameters")
            colour = column_colours(owners)
        g = n if colour is None else int(colour.max()) + 1  # directions to compute
        b = min(batch, -(-g // n_dev))
        # the directions padded with zero rows to a whole number of batches on every
        # device: lax.map would trace (and compile) leftover directions as a second,
        # smaller batch
        rows_pad = -(-g // (b * n_dev)) * b * n_dev
        if colour is None:
            eye = jnp.eye(rows_pad, n, dtype=u.dtype)
        else:  # each direction the sum of its columns' unit vectors
            eye = jnp.asarray(direction_seeds(colour, rows_pad), u.dtype)

        def columns(eye, u, args):
            # one trace of the chain: linearised once, its linear map applied to the
            # rows of eye (parameter directions), b at a time; an empty aux where raw
            # gives none
            def item(i):
                def with_aux(v):
                    out = at(v, args, i)
                    return out if has_aux else (out, ())

                y, column, aux = jax.linearize(with_aux, u, has_aux=True)
                return y, aux, jax.lax.map(column, eye, batch_size=b)

            y, aux, cols = each(item)
            if items is not None:  # directions first, then items
                cols = jax.tree_util.tree_map(lambda c: jnp.swapaxes(c, 0, 1), cols)
            return y, aux, cols

        if mesh is not None:  # each device its own rows of eye; y is the same on all
            columns = jax.shard_map(columns, mesh=mesh, in_specs=(P(AXIS), P(), P()),
                                    out_specs=(P(), P(), P(AXIS)), check_vma=False)
        y, aux, cols = columns(eye, u, args)
        if colour is None:
            dy = jax.tree_util.tree_map(lambda c: jnp.tensordot(du, c[:n], axes=1), cols)
        else:  # the G directions' derivatives kept as they are, not the P columns
            rows = jax.tree_util.tree_map(np.asarray, blocks[1])
            weights = _direction_weights(du, colour, owners, rows)
            dy = jax.tree_util.tree_map(lambda c, r: _compressed_tangent(c[:g], weights, r),
                                        cols, rows)
        if not has_aux:
            return y, dy
        return (y, aux), (dy, jax.tree_util.tree_map(jnp.zeros_like, aux))

    return fn


def _direction_weights(du, colour, owners, rows):
    """The tangent ``du`` (P,) as weights of the compressed directions on each block's
    rows, (G, B + 1): entry (g, c) is the tangent of the column of direction g that
    moves block c (the direction's shared column, or block c's own column of that
    direction; 0 where there is none), and the last, for rows in no block (``rows`` −1),
    only a shared column's. Linear in ``du``: a gather."""
    n_blocks = 1 + max([int(np.max(owners, initial=-1))]
                       + [int(np.max(r, initial=-1)) for r in jax.tree_util.tree_leaves(rows)])
    pick = np.full((int(colour.max()) + 1, n_blocks + 1), -1)
    for j, (g, o) in enumerate(zip(colour, owners)):
        if o < 0:
            pick[g, :] = j
        else:
            pick[g, o] = j
    return jnp.where(jnp.asarray(pick >= 0), du[np.maximum(pick, 0)], 0)


def _compressed_tangent(c, weights, rows):
    """J du on one output from its compressed directions' derivatives ``c`` (G, …) and
    :func:`_direction_weights` (G, B + 1): each residual's sum over the directions of
    the derivative times the weight for its block (``rows``, broadcastable to one
    output; −1: no block). G × residuals operations, and the linearisation keeps the G
    directions' derivatives, not the P columns (for a field of 120 stars, 17 against
    493). Contractions over the directions (``dot_general``), not a product summed
    over an axis: jaxlib 0.10.2's CPU compiler computes that sum wrongly under ``vmap``
    at these sizes, and takes seconds for it (its YNNPACK fusion; jax#39103)."""
    rows = np.asarray(rows)
    rows = np.where(rows < 0, weights.shape[1] - 1, rows)
    if rows.ndim == 0:  # the whole output one block's
        return jnp.tensordot(weights[:, int(rows)], c, axes=1)
    found = equal_blocks(rows) if rows.shape == c.shape[1:] else None
    if found is not None:  # equal contiguous blocks (the stars of a field)
        n_blocks, size = found
        return jnp.einsum("gkn,gk->kn", c.reshape(c.shape[0], n_blocks, size),
                          weights[:, :n_blocks]).reshape(rows.shape)
    w = weights[:, rows]  # (G,) + rows' shape
    w = w.reshape((w.shape[0],) + (1,) * (c.ndim - 1 - rows.ndim) + rows.shape)
    return jnp.einsum("g...,g...->...", c, jnp.broadcast_to(w, c.shape))


def gauss_newton_gain(jtj, g):
    """The largest fall of the loss ½|r|² that the linearisation allows, from its normal
    equations (``jtj`` = JᵀJ, ``g`` = Jᵀr, :func:`normal_equations`): ½ |J δ|² at the
    Gauss–Newton step δ (least squares of J δ = −r; directions the columns do not
    determine count for nothing). Column-scaled, solved by their eigenvalues (P × P for
    P parameters: cheap beside the Jacobian itself)."""
    scale = column_scale(jtj, jnp, fill=0.0)
    w, v = jnp.linalg.eigh(jtj * scale[:, None] * scale[None, :])
    keep = w > 1e-12 * jnp.max(w)
    proj = v.T @ (g * scale)
    return 0.5 * jnp.sum(jnp.where(keep, proj * proj / jnp.where(keep, w, 1.0), 0.0))


class StopRule:
    """The loss-based half of the stopping rule, for one solve: call :meth:`update`
    after every step with the loss of the last accepted point, the solver's count of
    accepted steps and, where known, :func:`gauss_newton_gain` at that point; it says
    whether to stop: a fall below ``ftol``, relative, over the last three accepted
    steps; a rejected step once a step was accepted, where the Gauss–Newton step from
    the accepted point promises less than that (no step the solver could still try
    would gain more, and each try costs a model evaluation); or :data:`MAX_REJECTED`
    rejections in a row once a step was accepted."""

    def __init__(self, ftol: float):
        self.ftol = float(ftol)
        self.history: list[float] = []
        self.accepted = 0
        self.rejected = 0

    def update(self, loss: float, accepted: int, gain: float | None = None) -> bool:
        if accepted > self.accepted:  # an accepted step: the loss moved to a new point
            self.history.append(loss)
            self.rejected = 0
        else:
            self.rejected += 1
        self.accepted = accepted
        h = self.history
        small = self.ftol * abs(loss)
        plateau = len(h) >= 4 and h[-4] - loss <= small
        settled = bool(h) and self.rejected > 0 and gain is not None and gain <= small
        return plateau or settled or (bool(h) and self.rejected >= MAX_REJECTED)


@dataclasses.dataclass
class SolveResult:
    u: jax.Array
    steps: int
    accepted: int
    loss_start: float
    loss: float
    result: str  # "converged", "failed" or "max_steps"
    seconds: float
    compile_seconds: float
    #: the solver's last state: its linearisation is at ``u`` (see
    #: :meth:`LMStepper.linearisation`); None where a solve did not keep it
    state: Any = dataclasses.field(default=None, repr=False)
    #: the aux of ``fn(u, args)`` at ``u`` (``LMStepper(..., has_aux=True)``), else None
    aux: Any = dataclasses.field(default=None, repr=False)


def _damping_for_length(jtj, g, target):
    """The smallest damping λ whose step −(JᵀJ + λI)⁻¹Jᵀr is at most ``target`` long
    (Euclidean), by bisection of log λ on the eigenvalues of JᵀJ (P × P; ``jtj``, ``g``
    = Jᵀr: :func:`normal_equations`); inf where no target or gradient makes sense."""
    w, v = jnp.linalg.eigh(jtj)
    w = jnp.maximum(w, 0.0)
    g = v.T @ g
    gnorm = jnp.sqrt(jnp.sum(g * g))
    hi = gnorm / jnp.where(target > 0, target, 1.0)  # λ ≥ |g|/target is always short enough
    lo = hi * 1e-16

    def length(lam):
        return jnp.sqrt(jnp.sum((g / (w + lam)) ** 2))

    def halve(_, bracket):
        lo, hi = bracket
        mid = jnp.sqrt(lo * hi)
        short = length(mid) <= target
        return jnp.where(short, lo, mid), jnp.where(short, mid, hi)

    _, hi = jax.lax.fori_loop(0, 60, halve, (lo, hi))
    ok = (target > 0) & (gnorm > 0) & jnp.isfinite(hi)
    return jnp.where(ok, hi, jnp.inf)


#: After a rejected step, or an accepted one whose loss fell by less than :data:`POOR`
#: of the predicted fall, the next is at most this fraction of its length
#: (:class:`ShrinkingTrustRegion`).
SHORTEN = 0.5

#: The fraction of its predicted fall below which an accepted step counts as poor (the
#: classical trust region's ¼: Nocedal & Wright, Algorithm 4.1).
POOR = 0.25


class ShrinkingTrustRegion(optx.ClassicalTrustRegion):
    """optimistix's trust-region update (accept, grow or shrink the step size by the
    ratio of the actual to the predicted fall of the loss), except that after a rejected
    step the next is at most :data:`SHORTEN` of the rejected one's length, as a trust
    region's radius shrinks (Nocedal & Wright, Algorithm 4.1). Levenberg–Marquardt's
    damping λ = 1/step size is in the units of JᵀJ, whose eigenvalues grow with the
    number of pixels and their weights (10⁴–10⁵ for a star's χ²): quartering the step
    size from 1, as optimistix does, shortens the directions whose curvature is below λ
    but leaves a Gauss–Newton step in the others as it was until λ reaches them, so a
    solve could spend ten model evaluations on nearly the same rejected step and stop
    there, short of a minimum that shorter steps would have found. Where quartering
    the step size already halves the step, the update is optimistix's.

    The same shortening follows an accepted step whose loss fell by less than
    :data:`POOR` of the predicted fall (optimistix keeps the step size for any accepted
    step): Gauss–Newton leaves out the residuals' own curvature, as large as JᵀJ at a
    minimum with a χ²/dof of a few, and its steps then overshoot by about 2×: the
    Spitzer star's rotation swung from side to side of its minimum for 25 steps, each
    accepted, each closing in by about 10 %."""

    #: the Jacobian's block structure (:class:`BlockColumns`), or None: dense
    structure: Any = eqx.field(static=True, default=None)

    def init(self, y, f_info_struct):
        # a strongly typed step size, as :meth:`step` returns it (the same program runs
        # every step)
        state = super().init(y, f_info_struct)
        return eqx.tree_at(lambda s: s.step_size, state,
                           jnp.asarray(state.step_size, dtype=jnp.result_type(float)))

    def step(self, first_step, y, y_eval, f_info, f_eval_info, state):
        size, accept, result, new = super().step(first_step, y, y_eval, f_info,
                                                 f_eval_info, state)
        y_diff = jax.tree_util.tree_map(lambda a, b: a - b, y_eval, y)
        diff = jnp.concatenate([jnp.ravel(d) for d in jax.tree_util.tree_leaves(y_diff)])
        # an accepted step whose loss fell by less than a quarter of the fall the
        # linearisation predicted overshot (Gauss–Newton leaves out the residuals' own
        # curvature, as large as JᵀJ at a minimum with χ²/dof of a few): the next step,
        # from the accepted point, is shortened as after a rejection, from there
        fell = f_eval_info.as_min() - f_info.as_min()
        poor = accept & jnp.invert(first_step) & (
            fell > POOR * self.predict_reduction(y_diff, f_info))
        target = SHORTEN * jnp.sqrt(jnp.sum(diff * diff))

        def shorter(info):  # the step size whose step from ``info``'s point is short enough
            lam = _damping_for_length(*normal_equations(info, self.structure), target)
            return jnp.minimum(size, jnp.where(jnp.isfinite(lam) & (lam > 0), 1.0 / lam, size))

        # only where the step is to be shortened, and from the one point it starts from
        # (the Jacobian materialised once, not on every accepted step)
        size = jax.lax.cond(accept & jnp.invert(poor), lambda: size,
                            lambda: jax.lax.cond(accept, lambda: shorter(f_eval_info),
                                                 lambda: shorter(f_info)))
        return size, accept, result, eqx.tree_at(lambda s: s.step_size, new, size)


class LevenbergMarquardt(optx.LevenbergMarquardt):
    """optimistix's Levenberg–Marquardt with :class:`ShrinkingTrustRegion`; where the
    Jacobian has a block structure (``structure``, :class:`BlockColumns`), its steps
    from the normal equations that structure gives (:class:`NormalDescent`)."""

    def __init__(self, rtol, atol, structure=None):
        super().__init__(rtol=rtol, atol=atol)
        self.search = ShrinkingTrustRegion(structure=structure)
        if structure is not None:
            self.descent = NormalDescent(structure)


class LMStepper:
    """Compiled solver steps for ``fn(u, args) -> residuals`` (``method`` "lm":
    Levenberg–Marquardt; "gn": Gauss–Newton with QR).

    The tolerances ``rtol`` and ``atol`` are arguments of the compiled programs, not
    constants of them: a solve may give its own (:meth:`solve`) and still run the
    programs another solve compiled (a fit's stages with other tolerances share them)."""

    def __init__(self, fn: Callable, *, method: str = "lm", rtol: float = 1e-6,
                 atol: float = 1e-6, has_aux: bool = False,
                 structure: BlockColumns | None = None):
        # has_aux: fn returns (residuals, aux); the solve's result then carries the aux
        # of its answer (SolveResult.aux), from the step that accepted it. structure:
        # the Jacobian's blocks (the stars of a field), whose normal equations then cost
        # pixels × (directions)² instead of pixels × (parameters)²
        wrapped = fn if has_aux else (lambda u, a: (fn(u, a), None))
        if method not in ("lm", "gn"):
            raise ValueError(f"solver method must be 'lm' or 'gn'; got {method!r}")
        if structure is not None and method != "lm":
            raise ValueError("LMStepper: a block structure needs method 'lm'")
        self.method = method
        self.structure = structure
        self.rtol, self.atol = float(rtol), float(atol)
        tags = frozenset()
        jit_options = solver_jit_options()  # a shorter compile on a CPU (see _xla)

        def init(sol, u, a):
            f_struct, aux_struct = jax.eval_shape(lambda: wrapped(u, a))
            return sol.init(wrapped, u, a, {}, f_struct, aux_struct, tags)

        def step(sol, u, state, a):
            accepted_before = state.num_accepted_steps
            u, state, _ = sol.step(wrapped, u, a, {}, state, tags)
            done, res = sol.terminate(wrapped, u, a, {}, state, tags)
            leaves = jax.tree_util.tree_leaves(state.f_info.residual)
            loss = 0.5 * sum(jnp.sum(r * r) for r in leaves)
            size = getattr(state.search_state, "step_size", jnp.asarray(1.0))
            # StopRule looks at the gain only after a rejected step: computed only then,
            # from the normal equations NormalDescent made when that point was accepted
            # (a block structure), or from the point's Jacobian (dense)
            def normal():
                if structure is not None:
                    return state.descent_state.jtj, state.descent_state.g
                return normal_equations(state.f_info)

            gain = jax.lax.cond(
                state.num_accepted_steps == accepted_before,
                lambda: gauss_newton_gain(*normal()).astype(loss.dtype),
                lambda: jnp.asarray(jnp.inf, loss.dtype))
            return u, state, done, res == optx.RESULTS.successful, loss, size, \
                state.num_accepted_steps, gain

        def linearisation(state):
            # the Jacobian and residuals the last accepted step was linearised at: the
            # step returns that point as u, so these are the ones at u
            r = jnp.concatenate([x.ravel() for x in
                                 jax.tree_util.tree_leaves(state.f_info.residual)])
            return state.f_info.jac.as_matrix(), r

        # compiled here with the solver's options; top-level programs only, since JAX
        # takes compiler options on no jit nested inside another
        self._init_with = eqx.filter_jit(init, **jit_options)
        self._step_with = Ahead(eqx.filter_jit(step, **jit_options))
        self._linearisation = eqx.filter_jit(linearisation, **jit_options)
        self._init_traced, self._step_traced = init, step

    def compile_ahead(self, u, args) -> None:
        """Compile the solver's step for a start and data of the shapes of ``u`` and
        ``args`` on the background thread (:mod:`difstar._ahead`) while the caller
        prepares the start (a photometric start compiles and runs the forward model:
        on a 2-core CPU the two compiles run side by side). The first state is made
        here (its trace is the chain's linearisation's). The next :meth:`solve` of those
        shapes runs the program compiled ahead, waiting for it if need be; a solve of
        other shapes compiles its own, as without this call. Once a stepper has a
        program compiled ahead, later calls do nothing (a study's fits share it)."""
        if self._step_with.started:
            return
        sol = self.solver()
        state = self._init_with(sol, u, args)  # traces the chain's linearisation
        self._step_with.compile_ahead(sol, u, state, args)

    def solver(self, rtol: float | None = None, atol: float | None = None):
        """The optimistix solver with these tolerances (default: the stepper's), as
        arrays: arguments of the compiled programs."""
        rtol = jnp.asarray(self.rtol if rtol is None else float(rtol), float)
        atol = jnp.asarray(self.atol if atol is None else float(atol), float)
        if self.method == "lm":
            return LevenbergMarquardt(rtol=rtol, atol=atol, structure=self.structure)
        return optx.GaussNewton(rtol=rtol, atol=atol, linear_solver=lx.QR())

    def _init(self, u, a):
        """The solver's first state at ``u`` (the stepper's tolerances), to be traced
        inside the caller's own jit (the batched fits)."""
        return self._init_traced(self.solver(), u, a)

    def _step(self, u, state, a):
        """One step from ``u``, ``state`` (the stepper's tolerances), to be traced
        inside the caller's own jit (the batched fits)."""
        return self._step_traced(self.solver(), u, state, a)

    def linearisation(self, result: SolveResult):
        """(J, r) at ``result.u``: the flattened residuals (leaves in tree order) and
        their Jacobian in ``u``, as NumPy arrays, taken from the solver's last
        linearisation (no compile of the model's Jacobian, no evaluation of the model)."""
        if result.state is None:
            raise ValueError("this solve kept no solver state; compute the Jacobian anew")
        j, r = self._linearisation(result.state)
        return np.asarray(j), np.asarray(r)

    def solve(self, u0, args, *, max_steps: int = 100, ftol: float = 1e-6,
              progress: Callable[[int, float, float, bool, np.ndarray], None] | None = None,
              rtol: float | None = None, atol: float | None = None) -> SolveResult:
        """Run up to ``max_steps`` steps from ``u0``; ``progress(k, loss, step_size,
        done, u)`` is called after each (loss of the last accepted point ``u``; the LM
        step size is the trust-region scale, 1/damping). ``rtol``, ``atol``: this solve's
        tolerances (default: the stepper's), without a new compile."""
        sol = self.solver(rtol, atol)
        state = self._init_with(sol, u0, args)
        u = u0
        loss0 = None
        loss = float("nan")
        t_compile = 0.0
        done = ok = False
        k = acc = 0
        rule = StopRule(ftol)
        t0 = time.perf_counter()
        for k in range(1, max_steps + 1):
            t1 = time.perf_counter()
            u, state, done_a, ok_a, loss_a, size, acc_a, gain = self._step_with(
                sol, u, state, args)
            loss = float(loss_a)
            if k == 1:
                t_compile = time.perf_counter() - t1
            done, ok = bool(done_a), bool(ok_a)
            if k == 2:  # the first step only evaluates the start
                loss0 = loss
            acc = int(acc_a)
            if rule.update(loss, acc, float(gain)) and not done:
                done = ok = True
            if progress is not None:
                progress(k, loss, float(size), done, np.asarray(u))
            if done:
                break
        return SolveResult(
            u=u, steps=k, accepted=acc, loss_start=loss if loss0 is None else loss0,
            loss=loss, result=("converged" if ok else "failed") if done else "max_steps",
            seconds=time.perf_counter() - t0 - t_compile, compile_seconds=t_compile,
            state=state, aux=state.aux,
        )
