"""Physics tests run in float64 (DESIGN.md: "Tests of physics run in float64")."""

import jax

jax.config.update("jax_enable_x64", True)
