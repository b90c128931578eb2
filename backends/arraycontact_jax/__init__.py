"""JAX back end of arraycontact: detection under `jax.jit` / `vmap`, differentiable.

plan(master, slave_points, ...) -> Plan       eager: sizes every buffer from the data
detect(plan, slave_points, master_points)     jitted: Contacts (a pytree) with overflow
update_plan(plan, contacts, slave_points, master_points) -> Plan   re-plan on overflow
plan_self(surface, ...), detect_self(plan, points)  self-contact (arraycontact.detect_self)
"""

from ._detect import Plan as Plan
from ._detect import detect as detect
from ._detect import detect_self as detect_self
from ._detect import plan as plan
from ._detect import plan_self as plan_self
from ._detect import run_one_shot as run_one_shot
from ._detect import update_plan as update_plan

__all__ = ["Plan", "detect", "detect_self", "plan", "plan_self", "run_one_shot", "update_plan"]
