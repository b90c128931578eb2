"""Spatial partition for detection on several devices (seed 004, "Recursive Coordinate
Bisectioning"; seed 000 section 4, MDMR).

The slaves and the master's faces (each face as its centre) are split by recursive coordinate
bisection: each cut is normal to the longest side of its set's box and divides the set's
weight in proportion to the parts on either side (any number of parts, not only powers of
two). A part owns its slaves; its *halo* holds every face whose ball comes within
`d_max + margin` of the box of those slaves, so a part detects its slaves alone, exactly as one
device would, as long as slaves and master nodes move less than `margin` between them (seed
004's capture boxes beyond the cut; seed 000's overlapping layer of cells). The *ring* adds
the faces sharing a node with the halo: the node normals, edges and boundary of every halo
face are then those of the whole master.

Host code (NumPy, float64): used by the JAX back end's sharded plan and by Warp users who
plan one device per part (`Partition.part`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._prepare import default_d_max
from ._surface import Surface, bounds, validate_points


@dataclass(frozen=True, eq=False)
class Part:
    """One part: its slaves, and its master as a Surface of its own (halo and ring faces, in
    the master's face order; nodes in the master's node order)."""

    slaves: np.ndarray  # rows of slave_points this part owns (sorted)
    faces: np.ndarray  # master face ids of the local master (sorted)
    nodes: np.ndarray  # master node ids of the local master's points (sorted)
    master: Surface  # local surface: points = master.points[nodes], faces renumbered


@dataclass(frozen=True, eq=False)
class Partition:
    """Recursive coordinate bisection of slaves and faces into `n_parts` parts.

    cuts: (axis, position, parts on the low side, parts in all) per cut, depth first from the
    root; regions [P, 2, 3]: each part's cell (outer sides at +-inf); slave_part [n] and
    face_part [F]: the owning part of each slave and face (a face by its centre);
    halo[p]: sorted face ids within `d_max + margin` of part p's slave box `boxes[p]` (or of
    its slaves one by one, `reached`);
    weights: what the cuts balanced, per part (`work`)."""

    n_parts: int
    cuts: tuple
    regions: np.ndarray
    slave_part: np.ndarray
    face_part: np.ndarray
    boxes: np.ndarray
    halo: tuple
    d_max: float
    margin: float
    work: np.ndarray
    master: Surface
    self_contact: bool = False

    def part(self, p: int) -> Part:
        """Part p's slaves and local master (its halo plus the ring of faces sharing a node)."""
        m = self.master
        used = np.zeros(len(m.points), bool)
        used[m.faces[self.halo[p]].ravel()] = True
        faces = np.flatnonzero(used[m.faces].any(1))
        # The faces' nodes and their local ids by a mask and a prefix sum (np.unique and
        # searchsorted over the part's faces took 1.4 s a part at 2^20 on a GPU host).
        on = np.zeros(len(m.points), bool)
        on[m.faces[faces]] = True
        nodes = np.flatnonzero(on)
        local = (np.cumsum(on) - 1)[m.faces[faces]]
        return Part(
            slaves=np.flatnonzero(self.slave_part == p),
            faces=faces,
            nodes=nodes,
            master=Surface(m.points[nodes], local, m.element),
        )

    def counts(self) -> dict:
        """Per part: owned slaves, halo faces and the weight the cuts balanced."""
        return dict(
            slaves=np.bincount(self.slave_part, minlength=self.n_parts),
            halo_faces=np.array([len(h) for h in self.halo]),
            work=self.work,
        )


def partition(
    master: Surface,
    slave_points=None,
    n_parts: int = 2,
    *,
    d_max=None,
    margin=None,
    weights=None,
    face_weights=None,
    self_contact=False,
    reached=None,
) -> Partition:
    """RCB of `slave_points` [n, 3] and `master`'s faces into `n_parts` parts, with halos.

    d_max: the detection distance (default: the seed's rule on `master`); margin: how far slaves
    and master nodes may move, together, before the halos no longer hold every face a slave
    can reach (default: half of d_max plus the largest face radius). weights: the work of each
    slave [n] (default 1; the JAX plan passes 1 + its candidate faces); face_weights: each
    face's [F] (default 1; the JAX plan passes 1 where a slave has the face as a candidate,
    else 0: a face no slave reaches costs no part anything).
    self_contact: the slaves are the master's nodes (`master.nodes`; slave_points not given).
    reached: when the caller can find the faces each slave reaches (the JAX plan, with its
    tree), a function of the slaves' parts [n] returning [n_parts, F] bools: whether a slave
    of the part has the face within d_max + margin. A part's halo is then the faces its own
    slaves reach, tighter than the faces that reach the box around them all."""
    if not isinstance(master, Surface):
        raise ValueError("master must be an arraycontact.Surface")
    if master.n_faces == 0:
        raise ValueError("master has no faces")
    if not (isinstance(n_parts, (int, np.integer)) and n_parts >= 1):
        raise ValueError(f"n_parts must be a positive integer, got {n_parts!r}")
    if self_contact:
        if slave_points is not None:
            raise ValueError(
                "self_contact: the slaves are the master's nodes; give no slave_points"
            )
        slave_x = master.points[master.nodes]
    else:
        slave_x = validate_points(slave_points, "slave_points")
    if len(slave_x) == 0:
        raise ValueError("slave_points is empty: there is nothing to partition")
    d_max = default_d_max(master) if d_max is None else float(d_max)
    if not d_max > 0:
        raise ValueError(f"d_max must be positive, got {d_max}")
    centres, radii = master.face_bounds
    r_max = float(radii.max())
    margin = 0.5 * (d_max + r_max) if margin is None else float(margin)
    if not margin >= 0:
        raise ValueError(f"margin must be >= 0, got {margin}")
    w_s = np.ones(len(slave_x)) if weights is None else np.asarray(weights, float)
    if w_s.shape != (len(slave_x),) or not (np.isfinite(w_s).all() and (w_s >= 0).all()):
        raise ValueError(f"weights must be {len(slave_x)} finite values >= 0")

    w_f = np.ones(master.n_faces) if face_weights is None else np.asarray(face_weights, float)
    if w_f.shape != (master.n_faces,) or not (np.isfinite(w_f).all() and (w_f >= 0).all()):
        raise ValueError(f"face_weights must be {master.n_faces} finite values >= 0")
    x = np.concatenate([slave_x, centres])
    w = np.concatenate([w_s, w_f])
    owner = np.zeros(len(x), np.int32)
    regions = np.empty((n_parts, 2, 3))
    cuts = []
    inf = np.full(3, np.inf)
    stack = [(np.arange(len(x)), 0, n_parts, -inf, inf)]
    while stack:
        idx, first, k, lo, hi = stack.pop()
        if k == 1:
            owner[idx] = first
            regions[first] = lo, hi
            continue
        left = k // 2
        axis, pos, n_low = _cut(x[idx], w[idx], left / k)
        order = np.argsort(x[idx, axis], kind="stable")
        cuts.append((int(axis), float(pos), left, k))
        hi_l, lo_r = hi.copy(), lo.copy()
        hi_l[axis] = lo_r[axis] = pos
        # Pushed right first: the low side is cut next (depth first, low before high).
        stack.append((idx[order[n_low:]], first + left, k - left, lo_r, hi))
        stack.append((idx[order[:n_low]], first, left, lo, hi_l))
    slave_part, face_part = owner[: len(slave_x)], owner[len(slave_x) :]

    boxes = np.empty((n_parts, 2, 3))
    halo = []
    reach = d_max + margin
    table = None if reached is None else np.asarray(reached(slave_part))
    if table is not None and table.shape != (n_parts, master.n_faces):
        raise ValueError(
            f"reached must return [n_parts, F] = {(n_parts, master.n_faces)}, got {table.shape}"
        )
    for p in range(n_parts):
        mine = slave_x[slave_part == p]
        if len(mine) == 0:  # a part with faces only: nothing to detect
            boxes[p] = np.inf, -np.inf
            halo.append(np.zeros(0, np.int64))
            continue
        lo, hi = bounds(mine)
        boxes[p] = lo, hi
        if table is not None:
            halo.append(np.flatnonzero(table[p]))
            continue
        out = np.maximum(np.maximum(lo - centres, centres - hi), 0)
        halo.append(np.flatnonzero(np.linalg.norm(out, axis=1) - radii <= reach))
    work = np.bincount(slave_part, w_s, n_parts) + np.bincount(face_part, w_f, n_parts)
    return Partition(
        n_parts=int(n_parts),
        cuts=tuple(cuts),
        regions=regions,
        slave_part=slave_part,
        face_part=face_part,
        boxes=boxes,
        halo=tuple(halo),
        d_max=d_max,
        margin=margin,
        work=work,
        master=master,
        self_contact=bool(self_contact),
    )


def _cut(x, w, share):
    """The cut of points x [m, 3] with weights w normal to their box's longest side, leaving
    `share` of the weight on the low side: (axis, position, items on the low side)."""
    lo, hi = bounds(x)
    axis = int(np.argmax(hi - lo))
    c = x[:, axis]
    order = np.argsort(c, kind="stable")
    cw = np.cumsum(w[order])
    # The first item whose running weight reaches the share, then the nearer of it and the one
    # before; at least one item on each side when there are two or more.
    k = int(np.searchsorted(cw, share * cw[-1]))
    if k > 0 and abs(cw[k - 1] - share * cw[-1]) <= abs(cw[min(k, len(cw) - 1)] - share * cw[-1]):
        k -= 1
    n_low = min(max(k + 1, 1), len(c) - 1) if len(c) > 1 else len(c)
    s = c[order]
    pos = 0.5 * (s[n_low - 1] + s[n_low]) if 0 < n_low < len(c) else float(s[-1])
    return axis, pos, n_low
