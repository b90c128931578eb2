"""JAX back end of arraycontact: the shared pipeline under `jax.jit` with static capacities."""

from ._detect import run_one_shot as run_one_shot

__all__ = ["run_one_shot"]
