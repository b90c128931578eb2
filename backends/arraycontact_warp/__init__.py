"""Warp back end of arraycontact: graph-capturable detection kernels and the geometry as
`@wp.func`s for simulators' own kernels.

    plan(master, slave_points, *, slave_world, master_world, d_max, device, dtype, mode)
        -> Plan
    detect(plan, slave_points, master_points) -> dict of arrays (launches only)
    plan_self(surface, *, world, ...), detect_self(plan, points): self-contact
        (arraycontact.detect_self's rule)
    plan_swept(master, slave_points, *, slave_world, master_world, device, dtype),
    detect_swept(plan, slave_x0, slave_x1, master_x0, master_x1): swept detection over a
        step (arraycontact.detect_swept's contract)
    partition(master, slave_points, n_parts, d_max=...) -> Partition: arraycontact.partition,
        the RCB cuts and halos of a plan per device (`Partition.part(e)`: each part's
        slaves and master, see the README's "Several GPUs")
    closest_point_triangle, closest_point_face, closest_point_edge, start_option_one,
    face_point, face_nodes, set_node: @wp.func (float32; `geometry("float64")` holds their
    float64 twins)
"""

AVAILABLE = True

from arraycontact._partition import Partition as Partition  # noqa: E402
from arraycontact._partition import partition as partition  # noqa: E402

from ._detect import Plan as Plan  # noqa: E402
from ._detect import SweptPlan as SweptPlan  # noqa: E402
from ._detect import detect as detect  # noqa: E402
from ._detect import detect_self as detect_self  # noqa: E402
from ._detect import detect_swept as detect_swept  # noqa: E402
from ._detect import master_scalars as master_scalars  # noqa: E402
from ._detect import plan as plan  # noqa: E402
from ._detect import plan_self as plan_self  # noqa: E402
from ._detect import plan_swept as plan_swept  # noqa: E402
from ._detect import run_one_shot as run_one_shot  # noqa: E402
from ._detect import run_swept as run_swept  # noqa: E402
from ._geometry import Element as Element  # noqa: E402
from ._geometry import FaceNodes as FaceNodes  # noqa: E402
from ._geometry import Quads as Quads  # noqa: E402
from ._geometry import closest_point_edge as closest_point_edge  # noqa: E402
from ._geometry import closest_point_face as closest_point_face  # noqa: E402
from ._geometry import closest_point_triangle as closest_point_triangle  # noqa: E402
from ._geometry import element_data as element_data  # noqa: E402
from ._geometry import face_nodes as face_nodes  # noqa: E402
from ._geometry import face_point as face_point  # noqa: E402
from ._geometry import quad_data as quad_data  # noqa: E402
from ._geometry import set_node as set_node  # noqa: E402
from ._geometry import start_option_one as start_option_one  # noqa: E402
from ._real import precision as _precision  # noqa: E402


def geometry(dtype="float32"):
    """The module of exported @wp.funcs and structs (closest_point_face, Element, ...) that
    compute in dtype: this package's own for float32, their twins for float64."""
    import importlib

    return importlib.import_module(_precision(dtype).__package__ + "._geometry")


__all__ = [
    "AVAILABLE",
    "Element",
    "FaceNodes",
    "Plan",
    "Quads",
    "closest_point_edge",
    "closest_point_face",
    "closest_point_triangle",
    "detect",
    "detect_self",
    "element_data",
    "face_nodes",
    "face_point",
    "geometry",
    "plan",
    "plan_self",
    "master_scalars",
    "quad_data",
    "run_one_shot",
    "run_swept",
    "set_node",
    "SweptPlan",
    "plan_swept",
    "detect_swept",
    "start_option_one",
]
