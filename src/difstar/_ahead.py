"""Programs compiled ahead, on a background thread, while the caller goes on.

On a 2-core CPU a fit's solver programs take seconds to compile, mostly on one core,
while the fit's Python work before it (a photometric start, another stage) leaves the
other core idle. :class:`Ahead` wraps a jitted function: :meth:`Ahead.compile_ahead`
traces, lowers and compiles it for given arguments on :data:`COMPILER`. A later call
with arguments of those shapes runs that program (waiting for it if need be), any other
call the jitted function itself. Results are the same either way: the program compiled
ahead is the one the jitted function would compile (the same lowering and options; the
persistent compilation cache serves both).

JAX traces in any thread, but the Python parts of a trace share the interpreter's lock
with the caller; only XLA's compile runs beside it. So the caller should make the large
traces itself first (the solver's first state, :meth:`difstar._lm.LMStepper.compile_ahead`)
and leave the lowering and the compile to the background."""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor

#: The one background thread that compiles programs ahead: one compile at a time, so
#: that at most one core is taken from the caller's own work.
COMPILER = ThreadPoolExecutor(max_workers=1, thread_name_prefix="difstar-compile")


class Ahead:
    """A jitted function (``jax.jit`` or ``equinox.filter_jit``) that may be compiled
    ahead. Calling it calls the program compiled ahead where the arguments fit it, else
    the jitted function."""

    def __init__(self, jitted):
        self.jitted = jitted
        self._future: Future | None = None

    @property
    def started(self) -> bool:
        """Whether a program has been compiled ahead (or is being compiled)."""
        return self._future is not None

    def compile_ahead(self, *args) -> None:
        """Trace, lower and compile for ``args`` on :data:`COMPILER`. Once a program has
        been started, later calls do nothing."""
        if self._future is None:
            self._future = COMPILER.submit(lambda: self.jitted.lower(*args).compile())

    def _program(self):
        if self._future is None:
            return None
        try:
            return self._future.result()
        except Exception:  # noqa: BLE001 - the jitted function compiles again and reports
            self._future = None
            return None

    def __call__(self, *args):
        program = self._program()
        if program is not None:
            try:
                return program(*args)
            except (TypeError, ValueError):  # other shapes than the program's
                pass
        return self.jitted(*args)


__all__ = ["COMPILER", "Ahead"]
