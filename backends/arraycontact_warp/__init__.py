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

from ._real import precision as _precision  # noqa: E402
from ._surface import master_scalars as master_scalars  # noqa: E402

#: The names of the float32 modules, imported on first use (`__getattr__`): about half a
#: second of Warp declaring their functions on a 2-core host, which a float64 call through
#: `arraycontact.detect` (its default) never needs: it goes to the float64 twins alone.
_DETECT = {
    "Plan", "SweptPlan", "detect", "detect_self", "detect_swept", "plan", "plan_self",
    "plan_swept",
}  # fmt: skip
_GEOMETRY = {
    "Element", "FaceNodes", "Quads", "closest_point_edge", "closest_point_face",
    "closest_point_triangle", "element_data", "face_nodes", "face_point", "quad_data",
    "set_node", "start_option_one",
}  # fmt: skip


def __getattr__(name):
    if name in _DETECT:
        return getattr(_precision("float32"), name)
    if name in _GEOMETRY:
        return getattr(geometry("float32"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | _DETECT | _GEOMETRY)


def geometry(dtype="float32"):
    """The module of exported @wp.funcs and structs (closest_point_face, Element, ...) that
    compute in dtype: this package's own for float32, their twins for float64."""
    import importlib

    return importlib.import_module(_precision(dtype).__package__ + "._geometry")


def run_one_shot(slave_x, master, d_max, dtype, mode, self_contact):
    """`arraycontact.detect(backend="warp")`, in dtype's modules alone (see _detect)."""
    return _precision(dtype).run_one_shot(slave_x, master, d_max, dtype, mode, self_contact)


def run_swept(x0, x1, master, m1, su, dtype):
    """`arraycontact.detect_swept(backend="warp")`, in dtype's modules alone (see _detect)."""
    return _precision(dtype).run_swept(x0, x1, master, m1, su, dtype)


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
