"""Batches over devices: shard a batch over a device mesh, map a function over it, solve
many fits at once, render spectral scenes sharded by wavelength; the multi-process
launch (``jax.distributed``) read from the environment. See docs/sharding.md."""

from ._batch import device_mesh as device_mesh
from ._distributed import init_distributed as init_distributed
from ._batch import lapack_in_turn as lapack_in_turn
from ._distributed import launch_from_env as launch_from_env
from ._batch import map_batch as map_batch
from ._batch import shard as shard
from ._batch import sharded_vmap as sharded_vmap
from ._batch import simulate_spectral as simulate_spectral
from ._batch_fits import solve_many as solve_many
from ._distributed import writes_output as writes_output

__all__ = [
    "device_mesh", "init_distributed", "lapack_in_turn", "launch_from_env", "map_batch",
    "shard", "sharded_vmap", "simulate_spectral", "solve_many", "writes_output",
]
