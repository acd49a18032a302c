"""Programs compiled ahead on the background thread (difstar._ahead)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from difstar._ahead import Ahead


def test_a_program_compiled_ahead_serves_its_shapes_and_others_fall_back():
    calls = []

    def f(x, y):
        calls.append(x.shape)  # traced once per shape
        return jnp.sin(x) * y + jnp.sum(x)

    g = Ahead(jax.jit(f))
    assert not g.started
    x = jnp.linspace(0.0, 1.0, 7)
    g.compile_ahead(x, 2.0)
    assert g.started
    program = g._program()  # waits for the background thread, which traced f
    assert program is not None and calls == [(7,)]
    xs = np.linspace(0.0, 1.0, 7) + 1.0  # the truth in NumPy
    np.testing.assert_allclose(np.asarray(g(x + 1.0, 3.0)), np.sin(xs) * 3.0 + xs.sum(),
                               rtol=1e-14)
    assert calls == [(7,)]  # the program compiled ahead ran: no new trace
    g.compile_ahead(x[:3], 2.0)  # started already: nothing more
    assert g._program() is program and calls == [(7,)]
    y = jnp.arange(4.0)  # other shapes: the jitted function traces and compiles its own
    np.testing.assert_allclose(np.asarray(g(y, 2.0)), np.sin(np.arange(4.0)) * 2.0 + 6.0)
    assert calls == [(7,), (4,)]


def test_a_compile_that_fails_ahead_is_left_to_the_jitted_function():
    class Failing:
        def __init__(self):
            self.called = 0

        def lower(self, *args):
            return self

        def compile(self):
            raise RuntimeError("no memory for this compile")

        def __call__(self, *args):
            self.called += 1
            return "jitted"

    f = Failing()
    g = Ahead(f)
    g.compile_ahead(1)
    assert g(1) == "jitted" and f.called == 1 and not g.started


def test_errors_inside_the_program_are_not_swallowed():
    g = Ahead(jax.jit(lambda x: x[jnp.array([0, 1])] + 1))
    g.compile_ahead(jnp.zeros(3))
    with pytest.raises(TypeError):
        g(jnp.zeros(3), jnp.zeros(3))  # a call the jitted function refuses as well
