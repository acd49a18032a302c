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

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx

#: Consecutive rejected steps after which a solve that has moved counts as converged:
#: the trust region has shrunk by about 2^10 and no nearby point is lower.
MAX_REJECTED = 10


class StopRule:
    """The loss-based half of the stopping rule, for one solve: call :meth:`update`
    after every step with the loss of the last accepted point and the solver's count of
    accepted steps; it says whether to stop (a fall below ``ftol``, relative, over the
    last three accepted steps, or :data:`MAX_REJECTED` rejections in a row once a step
    was accepted)."""

    def __init__(self, ftol: float):
        self.ftol = float(ftol)
        self.history: list[float] = []
        self.accepted = 0
        self.rejected = 0

    def update(self, loss: float, accepted: int) -> bool:
        if accepted > self.accepted:  # an accepted step: the loss moved to a new point
            self.history.append(loss)
            self.rejected = 0
        else:
            self.rejected += 1
        self.accepted = accepted
        h = self.history
        plateau = len(h) >= 4 and h[-4] - loss <= self.ftol * abs(loss)
        return plateau or (bool(h) and self.rejected >= MAX_REJECTED)


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


class LMStepper:
    """Compiled solver steps for ``fn(u, args) -> residuals`` (``method`` "lm":
    Levenberg–Marquardt; "gn": Gauss–Newton with QR)."""

    def __init__(self, fn: Callable, *, method: str = "lm", rtol: float = 1e-6,
                 atol: float = 1e-6):
        wrapped = lambda u, a: (fn(u, a), None)  # noqa: E731
        if method == "lm":
            sol = optx.LevenbergMarquardt(rtol=rtol, atol=atol)
        elif method == "gn":
            sol = optx.GaussNewton(rtol=rtol, atol=atol, linear_solver=lx.QR())
        else:
            raise ValueError(f"solver method must be 'lm' or 'gn'; got {method!r}")
        self.method = method
        tags = frozenset()

        @eqx.filter_jit
        def init(u, a):
            f_struct = jax.eval_shape(lambda: fn(u, a))
            return sol.init(wrapped, u, a, {}, f_struct, None, tags)

        @eqx.filter_jit
        def step(u, state, a):
            u, state, _ = sol.step(wrapped, u, a, {}, state, tags)
            done, res = sol.terminate(wrapped, u, a, {}, state, tags)
            leaves = jax.tree_util.tree_leaves(state.f_info.residual)
            loss = 0.5 * sum(jnp.sum(r * r) for r in leaves)
            size = getattr(state.search_state, "step_size", jnp.asarray(1.0))
            return u, state, done, res == optx.RESULTS.successful, loss, size, \
                state.num_accepted_steps

        self._init, self._step = init, step

    def solve(self, u0, args, *, max_steps: int = 100, ftol: float = 1e-6,
              progress: Callable[[int, float, float, bool], None] | None = None
              ) -> SolveResult:
        """Run up to ``max_steps`` steps from ``u0``; ``progress(k, loss, step_size,
        done)`` is called after each (loss of the last accepted point; the LM step size
        is the trust-region scale, 1/damping)."""
        state = self._init(u0, args)
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
            u, state, done_a, ok_a, loss_a, size, acc_a = self._step(u, state, args)
            loss = float(loss_a)
            if k == 1:
                t_compile = time.perf_counter() - t1
            done, ok = bool(done_a), bool(ok_a)
            if k == 2:  # the first step only evaluates the start
                loss0 = loss
            acc = int(acc_a)
            if rule.update(loss, acc) and not done:
                done = ok = True
            if progress is not None:
                progress(k, loss, float(size), done)
            if done:
                break
        return SolveResult(
            u=u, steps=k, accepted=acc, loss_start=loss if loss0 is None else loss0,
            loss=loss, result=("converged" if ok else "failed") if done else "max_steps",
            seconds=time.perf_counter() - t0 - t_compile, compile_seconds=t_compile,
        )
