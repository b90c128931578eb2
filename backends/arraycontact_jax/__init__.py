"""JAX back end of arraycontact: detection under `jax.jit` / `vmap`, differentiable.

plan(master, slave_points, ...) -> Plan       eager: sizes every buffer from the data
detect(plan, slave_points, master_points)     jitted: Contacts (a pytree) with overflow
update_plan(plan, contacts, slave_points, master_points) -> Plan   re-plan on overflow
plan_self(surface, ...), detect_self(plan, points)  self-contact (arraycontact.detect_self)
plan_swept(master, slave_x0, slave_x1, master_x1) -> SweptPlan   swept detection over a step
detect_swept(plan, slave_x0, slave_x1, master_x0, master_x1)     jitted SweptContacts
update_swept_plan(plan, result, slave_x0, slave_x1, master_x0, master_x1)   on overflow
"""

from ._detect import Plan as Plan
from ._detect import SweptPlan as SweptPlan
from ._detect import detect as detect
from ._detect import detect_self as detect_self
from ._detect import detect_swept as detect_swept
from ._detect import plan as plan
from ._detect import plan_self as plan_self
from ._detect import plan_swept as plan_swept
from ._detect import run_one_shot as run_one_shot
from ._detect import run_swept as run_swept
from ._detect import update_plan as update_plan
from ._detect import update_swept_plan as update_swept_plan

__all__ = [
    "Plan",
    "SweptPlan",
    "detect",
    "detect_self",
    "detect_swept",
    "plan",
    "plan_self",
    "plan_swept",
    "run_one_shot",
    "run_swept",
    "update_plan",
    "update_swept_plan",
]
