"""The optimisers of :func:`difstar.design`: the names it knows (:data:`OPTIMISERS`), the
one place that decides how an optimiser runs (:func:`optimiser_kind`), the
bound-constrained quasi-Newton :class:`LBFGSB`, and the three step loops (optax,
optimistix, L-BFGS-B), each compiled once and stepped from Python so that every
iterate is recorded."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

from ._design_measures import Real
from ._validate import InputError, check_number


class LBFGSB(eqx.Module):
    """Bound-constrained quasi-Newton (L-BFGS-B, ``jaxopt.LBFGSB``) for :func:`design`,
    working in the bounded parameters themselves (each as its fraction of its range, an
    affine rescaling): no sigmoid map, so a parameter can sit exactly on its bound
    (where the optimum of a bounded design often is) and every iterate stays inside the
    bounds (each step ends on the segment from the iterate to a point of the box;
    rounding is clipped off).

    history: correction pairs kept (the memory of the Hessian approximation).
    tol: stop once the projected gradient's largest component is at most ``tol`` (in
        the objective's units per parameter range); 0 (the default) runs every step,
        but a line search that cannot lower the objective twice running (the second
        time from the projected gradient, the memory dropped) also stops it.
    max_linesearch: objective evaluations per line search at most.
    first_step: the first step's largest move, as a fraction of that parameter's range
        (the quasi-Newton matrix starts as a multiple of the identity, so the objective's
        units would set it otherwise); later steps are scaled by the curvature seen.

    Each iteration is one line search (usually one objective-and-gradient evaluation
    and, in jaxopt, one value-only evaluation at its start; more when the step has to be
    shortened). Compiling the step takes several times as long as an Adam step (jaxopt's
    line search holds the objective in several branches): it pays on longer runs and on
    optima on the bounds (BENCHMARKS.md, "Design optimisers"). jaxopt is no longer
    maintained (its authors point to optax, which has no bound-constrained L-BFGS); its
    import-time DeprecationWarning is silenced where it is imported, in :meth:`solver`.
    """

    history: int = eqx.field(static=True, default=10)
    tol: Real = eqx.field(static=True, default=0.0)
    max_linesearch: int = eqx.field(static=True, default=30)
    first_step: Real = eqx.field(static=True, default=0.1)

    def __check_init__(self):
        check_number(self.history, "LBFGSB.history", integer=True, ge=1, le=1000,
                     fix="correction pairs kept, e.g. 10")
        check_number(self.tol, "LBFGSB.tol", ge=0,
                     fix="a projected-gradient tolerance, or 0 to run every step")
        check_number(self.max_linesearch, "LBFGSB.max_linesearch", integer=True, ge=1,
                     le=1000, fix="objective evaluations per line search, e.g. 30")
        check_number(self.first_step, "LBFGSB.first_step", gt=0, le=1,
                     fix="a fraction of the parameters' ranges, e.g. 0.1")

    def solver(self, loss: Callable):
        """The ``jaxopt.LBFGSB`` minimising ``loss(params) -> (value, aux)``."""
        import warnings

        with warnings.catch_warnings():  # "JAXopt is no longer maintained" (0.8.5)
            warnings.filterwarnings("ignore", category=DeprecationWarning,
                                    module="jaxopt")
            warnings.filterwarnings("ignore", message=".*JAXopt.*",
                                    category=DeprecationWarning)
            import jaxopt

        # max_stepsize 1: a step never goes past the projected quasi-Newton point, which
        # lies in the box, so the iterates stay feasible
        return jaxopt.LBFGSB(fun=loss, has_aux=True, tol=self.tol,
                             history_size=self.history, maxls=self.max_linesearch,
                             max_stepsize=1.0)


#: the optimisers :func:`design` knows by name, each with its defaults
OPTIMISERS = {"adam": "optax.adam(0.1) on the sigmoid-unconstrained values of the bounds",
              "lbfgsb": "LBFGSB(): bound-constrained quasi-Newton in the parameters"}


def optimiser_kind(optimiser) -> tuple[str, Any]:
    """The one place that decides how :func:`design` runs an optimiser: returns
    (``"optax"`` | ``"optimistix"`` | ``"lbfgsb"``, the optimiser object), turning the
    names of :data:`OPTIMISERS` (and None, Adam) into their default objects. Anything
    else is refused with the accepted forms."""
    if optimiser is None or (isinstance(optimiser, str) and optimiser == "adam"):
        import optax

        return "optax", optax.adam(0.1)
    if isinstance(optimiser, str):
        if optimiser == "lbfgsb":
            return "lbfgsb", LBFGSB()
        raise InputError(f"optimiser: {optimiser!r} is not a known optimiser; give one of "
                         f"{', '.join(map(repr, OPTIMISERS))}, an optax "
                         "GradientTransformation, an optimistix minimiser or "
                         "difstar._design.LBFGSB(...).")
    if isinstance(optimiser, LBFGSB):
        return "lbfgsb", optimiser
    import optimistix as optx

    if isinstance(optimiser, optx.AbstractMinimiser):
        return "optimistix", optimiser
    if callable(getattr(optimiser, "init", None)) and callable(
            getattr(optimiser, "update", None)):
        return "optax", optimiser
    raise InputError(f"optimiser: a {type(optimiser).__name__} is not an optimiser; give "
                     f"one of {', '.join(map(repr, OPTIMISERS))}, an optax "
                     "GradientTransformation, an optimistix minimiser or "
                     "difstar._design.LBFGSB(...).")



def _unit_box(bounds):
    """(to_params, to_unit, unit bounds) for :class:`LBFGSB`: each bounded parameter as
    its fraction t ∈ [0, 1] of its range, p = lower + (upper − lower) t — an affine
    rescaling (a diagonal preconditioner), not a reparametrisation: p is exactly
    ``lower`` at t = 0 and exactly ``upper`` at t = 1 (rounding is clipped off), and
    dp/dt = upper − lower everywhere, bounds included. Fixed parameters (a range of zero
    width) stay at their value. Unbounded (None): the parameters themselves."""
    if bounds is None:
        return (lambda t: t), (lambda p: p), None
    lower, upper = bounds

    def up(lo, hi, t):
        span = hi - lo
        affine = lo + span * t
        exact = jnp.where(t >= 1, hi, jnp.where(t <= 0, lo, jnp.clip(affine, lo, hi)))
        return affine + jax.lax.stop_gradient(exact - affine)

    def down(lo, hi, p):
        span = hi - lo
        free = span > 0
        t = jnp.clip((p - lo) / jnp.where(free, span, 1.0), 0.0, 1.0)
        return jnp.where(free, t, 0.0)

    unit = (jax.tree.map(jnp.zeros_like, lower),
            jax.tree.map(lambda lo, hi: jnp.where(hi > lo, 1.0, 0.0).astype(lo.dtype),
                         lower, upper))
    return (lambda t: jax.tree.map(up, lower, upper, t),
            lambda p: jax.tree.map(down, lower, upper, p), unit)


def run_lbfgsb(fn, params0, bounds, optimiser: LBFGSB, steps, record, callback):
    """L-BFGS-B from ``params0`` (projected into the bounds: a copy, the input is not
    touched), one compiled iteration at a time (an attempt whose line search fails
    counts as one), on the parameters as fractions of their ranges (:func:`_unit_box`)
    and on the objective scaled so that its start's largest gradient component there
    is ``optimiser.first_step``: the first step (a projected gradient step: the
    quasi-Newton matrix starts as the identity) then moves that parameter by that
    fraction of its range, not by a length set by the objective's units. Stops after
    ``steps`` iterations, when the projected gradient is within ``optimiser.tol`` (in
    the objective's own units per range), when a line search fails right after a
    restart from the projected gradient (no lower value along either step) or when
    ``callback`` returns True."""
    to_params, to_unit, unit = _unit_box(bounds)

    def scaled(t, scale):
        val, aux = fn(to_params(t))
        return val * scale, aux

    solver = optimiser.solver(scaled)
    t = to_unit(jax.tree.map(jnp.asarray, params0))
    g0 = eqx.filter_jit(jax.grad(lambda t_: fn(to_params(t_))[0]))(t)
    g_max = max((float(jnp.max(jnp.abs(g))) for g in jax.tree.leaves(g0)), default=0.0)
    scale = jnp.asarray(optimiser.first_step / g_max if g_max > 0 else 1.0)
    state = eqx.filter_jit(solver.init_state)(t, unit, scale)
    extra = 1  # the gradient that set the scale

    def report(t_, st):
        p_ = to_params(t_)
        record(p_, st.value / scale, st.aux, st.num_fun_eval + extra)
        return p_

    p = report(t, state)

    @eqx.filter_jit
    def step(t_, st):
        return solver.update(t_, st, unit, scale)

    def restart(st, counts):
        """The state with the curvature memory dropped (the next step is a projected
        gradient step again), keeping the evaluation counts of ``counts``."""
        zeros = jax.tree.map(jnp.zeros_like, (st.s_history, st.y_history))
        return st._replace(s_history=zeros[0], y_history=zeros[1],
                           num_updates=jnp.zeros_like(st.num_updates),
                           theta=jnp.ones_like(st.theta),
                           stepsize=jnp.ones_like(st.stepsize),
                           num_fun_eval=counts.num_fun_eval,
                           num_grad_eval=counts.num_grad_eval)

    restarted = False
    for i in range(steps):
        t_new, new = step(t, state)
        if bool(new.failed_linesearch) and not float(new.value) < float(state.value):
            # no lower value along the quasi-Newton direction: once, drop the memory
            # and try the projected gradient; twice in a row, stop
            if restarted:
                break
            state, restarted = restart(state, new), True
            continue
        t, state, restarted = t_new, new, False
        p = report(t, state)
        if callback is not None and callback(i, p, float(state.value / scale), state.aux):
            break
        if float(state.error) / float(scale) <= optimiser.tol:
            break
    return p


def run_optax(loss, u, optimiser, steps, record, callback, to_params):
    import optax

    opt_state = optimiser.init(eqx.filter(u, eqx.is_inexact_array))

    @eqx.filter_jit
    def step(u_, state):
        (val, aux), g = eqx.filter_value_and_grad(loss, has_aux=True)(u_)
        updates, state = optimiser.update(g, state, u_)
        return optax.apply_updates(u_, updates), state, val, aux

    evaluate = eqx.filter_jit(loss)
    for i in range(steps):
        u_new, opt_state, val, aux = step(u, opt_state)
        record(u, val, aux)
        if callback is not None and callback(i, to_params(u), float(val), aux):
            u = u_new
            break
        u = u_new
    val, aux = evaluate(u)
    record(u, val, aux)
    return u


def run_optimistix(loss, u, solver, steps, record, callback, to_params):
    def fn(y, args):
        val, aux = loss(y)
        return val, (val, aux)

    f_struct, aux_struct = jax.eval_shape(fn, u, None)
    tags = frozenset()
    state = eqx.filter_jit(solver.init)(fn, u, None, {}, f_struct, aux_struct, tags)
    evaluate = eqx.filter_jit(loss)
    val, aux = evaluate(u)
    record(u, val, aux)

    @eqx.filter_jit
    def step(y, st):
        y, st, _ = solver.step(fn, y, None, {}, st, tags)
        done, _ = solver.terminate(fn, y, None, {}, st, tags)
        return y, st, done

    for i in range(steps):
        u, state, done = step(u, state)
        val, aux = evaluate(u)
        record(u, val, aux)
        if callback is not None and callback(i, to_params(u), float(val), aux):
            break
        if bool(done):
            break
    return u
