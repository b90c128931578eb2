"""JAX back end of arraycontact: detection under `jax.jit` / `vmap`, differentiable.

plan(master, slave_points, ...) -> Plan       eager: sizes every buffer from the data
detect(plan, slave_points, master_points)     jitted: Contacts (a pytree) with overflow
update_plan(plan, contacts, slave_points, master_points) -> Plan   re-plan on overflow
"""

from ._detect import Plan as Plan
from ._detect import detect as detect
from ._detect import plan as plan
from ._detect import run_one_shot as run_one_shot
from ._detect import update_plan as update_plan

__all__ = ["Plan", "detect", "plan", "run_one_shot", "update_plan"]
