"""Stage 1 (seed 000 section 2.1): d_max, bounding boxes and the nodes and faces that go on.

Runs eagerly in float64 on the host. The slave box and the master box, each grown by d_max
(eq. 4), are intersected; when they do not meet, detection ends here, before any grid is built.
Only slaves inside the intersection, master nodes inside it and faces whose ball reaches it go
on. The intersection's lower corner is the origin of the local frame in which everything after
this stage computes in float32 (so float32 keeps its precision far from the global origin). In
float64 the frame stays global: every distance is then taken between nearby values, which
subtract exactly, so even patches 10^6 box widths apart lose nothing to a shared origin.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._grid import consecutive, grouping, morton_keys
from ._surface import bounds, in_box


def default_d_max(master, displacement=None, longest_edge=None) -> float:
    """Seed 000: the longest master edge (eq. 2), raised to 2 max|dx| with displacements (eq. 3).
    longest_edge: the master's, when the caller has it (made on a device)."""
    d = master.longest_edge if longest_edge is None else longest_edge
    if displacement is not None:
        u = np.asarray(displacement, float)
        if u.ndim != 2 or u.shape[1] != 3 or not np.isfinite(u).all():
            raise ValueError(f"displacement must be a finite [n, 3] array, got shape {u.shape}")
        if len(u):
            d = max(d, 2.0 * float(np.linalg.norm(u, axis=1).max()))
    return float(d)


@dataclass(frozen=True, eq=False)
class Prepared:
    slave_rows: np.ndarray  # slaves inside the box
    node_ids: np.ndarray  # master nodes inside the box, in Morton order (the node tree's)
    face_ids: np.ndarray  # master faces whose ball reaches the box, in Morton order
    origin: np.ndarray  # local frame origin (float64)
    d_max: float
    r_max: float  # the largest face radius, for rounding slack
    node_groups: tuple  # the trees' slots per level (_grid.grouping)
    face_groups: tuple
    extent: float  # largest local coordinate, for rounding slack

    @property
    def node_levels(self) -> tuple:
        """The node tree's slots per level (its static shape)."""
        return tuple(len(g) for g in self.node_groups)

    @property
    def face_levels(self) -> tuple:
        return tuple(len(g) for g in self.face_groups)


def ordered(ids, x, lo, extent):
    """ids in the Morton order of their points x [len(ids), 3] over the cube [lo, lo +
    extent], and the tree's slots for that order (_grid.grouping)."""
    keys = morton_keys(x, lo, extent)
    order = np.argsort(keys, kind="stable")
    return ids[order], grouping(keys[order])


def slaves_in_box(slave_x, m_lo, m_hi, d_max):
    """The box where the slaves' box and the master's (m_lo, m_hi: of its nodes, or of its
    faces' balls where faces are curved), each grown by d_max (eq. 4), meet, and the rows of
    the slaves inside it: (rows, lo, hi), or None when there are none."""
    s_lo, s_hi = bounds(slave_x)
    lo = np.maximum(s_lo, m_lo) - d_max
    hi = np.minimum(s_hi, m_hi) + d_max
    if (lo > hi).any():
        return None
    rows = np.nonzero(in_box(slave_x, lo, hi))[0]
    return (rows, lo, hi) if len(rows) else None


def prepare(slave_x, master, d_max, dtype=np.float64, order=True) -> Prepared | None:
    """Boxes and selections, or None when the slave and master boxes do not meet. order=False:
    node_ids and face_ids in id order (for a back end that builds its own trees)."""
    if len(slave_x) == 0 or master.n_faces == 0:
        return None
    centres, radii = master.face_bounds
    used = master.points[master.nodes]
    if master.element.linear:
        m_lo, m_hi = master.node_box
    else:  # curved faces may bulge past their nodes; their balls hold them
        m_lo, m_hi = bounds(centres - radii[:, None])[0], bounds(centres + radii[:, None])[1]
    cut = slaves_in_box(slave_x, m_lo, m_hi, d_max)
    if cut is None:
        return None
    slave_rows, lo, hi = cut
    s = slave_x[slave_rows]
    s_lo, s_hi = bounds(s)
    lo = np.maximum(lo, s_lo - d_max)  # shrink to the slaves actually inside
    hi = np.minimum(hi, s_hi + d_max)
    node_ids = master.nodes[in_box(used, lo, hi)]
    # Faces whose ball comes within d_max of the box (squared, with room for the rounding of
    # the square: a face more is harmless; norm() took 6 ms of a 2^16 one-shot call).
    o = np.maximum(lo - centres, centres - hi)
    np.maximum(o, 0, out=o)
    o *= o
    reach = radii + d_max
    face_ids = np.nonzero(o[:, 0] + o[:, 1] + o[:, 2] <= reach * reach * (1 + 1e-12))[0]
    r_max = float(radii[face_ids].max()) if len(face_ids) else 0.0
    origin = lo if np.dtype(dtype) == np.float32 else np.zeros(3)
    extent = float((hi - lo).max())
    if order:
        node_ids, node_groups = ordered(node_ids, master.points[node_ids], lo, extent)
        face_ids, face_groups = ordered(face_ids, centres[face_ids], lo, extent)
    else:
        node_groups, face_groups = consecutive(len(node_ids)), consecutive(len(face_ids))
    return Prepared(
        slave_rows=slave_rows,
        node_ids=node_ids,
        face_ids=face_ids,
        origin=origin,
        d_max=float(d_max),
        r_max=r_max,
        node_groups=node_groups,
        face_groups=face_groups,
        extent=float(np.abs(np.r_[lo - origin, hi - origin]).max()),
    )
