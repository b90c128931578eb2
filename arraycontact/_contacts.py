"""The result record shared by every back end."""

from __future__ import annotations

import functools
import operator
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np


class Feature(IntEnum):
    """What the closest point lies on."""

    NONE = -1
    FACE = 0
    EDGE = 1
    VERTEX = 2


class Status(IntEnum):
    """Why a slave has no match, or a special one."""

    OK = 0  # active: the closest point is within d_max
    OUT_OF_RANGE = 1  # no master surface (exact) / no master node (node mode) within d_max
    BLIND_SPOT = 2  # node mode: no projection; contact with the closest attached face
    PASSING_BY = 3  # node mode: no projection and outside the proximal volume (eq. 13)
    NOT_CONVERGED = 4  # active, but the chosen projection did not meet its KKT tolerance
    # Self-contact, node mode: this node is the master side of its pair (seed 000 section 3,
    # item 5: its local mesh is coarser than its closest node's, or as fine with no
    # projection and the larger id); the contact element is the other node's row.
    MASTER_SIDE = 5


@dataclass(frozen=True)
class Counts:
    """Work counters of one detection: `count` may exceed `capacity` (overflow)."""

    slaves_in_box: int = 0  # the slaves inside the box where both surfaces' boxes meet
    # The master's nodes and faces the trees hold: those in that box (NumPy, JAX) or every
    # used node and face (Warp, whose trees hold the whole master).
    master_nodes_in_box: int = 0
    master_faces_in_box: int = 0
    count: dict = field(default_factory=dict)
    capacity: dict = field(default_factory=dict)

    @property
    def overflow(self) -> bool:
        # `|` rather than any(): the counts may be traced JAX scalars inside a jitted function.
        flags = [
            self.count[k] > self.capacity[k] for k in self.capacity if self.capacity[k] is not None
        ]
        return functools.reduce(operator.or_, flags, False)


@dataclass(frozen=True)
class Contacts:
    """One row per slave node.

    `face` is -1 and the geometric fields are NaN where `active` is false (except in node mode,
    where a passing-by slave keeps its closest geometry for inspection). `gap` is the signed
    distance along `normal` (negative: penetration), `distance` = |gap|. `slave_ids` are the
    slaves' node ids when the slaves came from a Surface, else 0..n-1. `backend`, `device` and
    `dtype` say what answered (with `backend="auto"`, the back end it chose)."""

    active: np.ndarray
    face: np.ndarray
    xi: np.ndarray
    point: np.ndarray
    gap: np.ndarray
    distance: np.ndarray
    normal: np.ndarray
    feature: np.ndarray
    master_node: np.ndarray
    status: np.ndarray
    slave_ids: np.ndarray
    d_max: float
    counts: Counts = field(default_factory=Counts)
    timings: dict = field(default_factory=dict)
    backend: str = ""  # the back end that answered ("numpy", "jax", "warp")
    device: str = ""  # where it ran ("cpu", "cuda:0", ...)
    dtype: str = ""  # the precision it computed in ("float64", "float32")
    # Self-contact: the slave node's local mesh is at least as fine as the face's (seed 000
    # section 3, item 5: keep the element of a pair from its finer side); None otherwise.
    finer: np.ndarray | None = None

    @property
    def overflow(self) -> bool:
        return self.counts.overflow

    def __len__(self):
        return len(self.active)

    def pairs(self) -> np.ndarray:
        """Contact elements [n_active, 2]: (slave node id, master face id)."""
        a = np.asarray(self.active)
        return np.stack([np.asarray(self.slave_ids)[a], np.asarray(self.face)[a]], -1)

    def summary(self) -> str:
        a = np.asarray(self.active)
        gap = np.asarray(self.gap)[a]
        lines = [f"backend: {self.backend or '?'} on {self.device or '?'}, {self.dtype or '?'}"]
        lines += [
            f"slaves: {len(a)}  active: {int(a.sum())}  contact elements: {len(self.pairs())}",
            f"d_max: {self.d_max:.6g}  min gap: {gap.min() if len(gap) else float('nan'):.6g}",
        ]
        st = np.bincount(np.asarray(self.status), minlength=len(Status))
        lines.append("status: " + ", ".join(f"{s.name.lower()} {st[s]}" for s in Status if st[s]))
        return "\n".join(lines)


@dataclass(frozen=True)
class SweptContacts:
    """One row per slave node: its first contact with the master over a step (detect_swept).

    `hit`: the node lies on a master face at some t in [0, 1]. `toi`: the earliest such t
    (never after the exact one, at most `t_tol` before it; inf where no hit); `face`, `xi`,
    `feature` of that contact; `point`: the node's position then; `normal`: the face's unit
    outward normal there and then; `normal_velocity`: the node's velocity relative to the face
    point along that normal, per step (negative: arriving at the face's front). `status`: OK,
    OUT_OF_RANGE (no hit) or NOT_CONVERGED (the search's budget ran out: the answer is still
    never late). `static`: the end-of-step Contacts when asked for (static=True)."""

    hit: np.ndarray
    toi: np.ndarray
    face: np.ndarray
    xi: np.ndarray
    point: np.ndarray
    normal: np.ndarray
    feature: np.ndarray
    normal_velocity: np.ndarray
    status: np.ndarray
    slave_ids: np.ndarray
    t_tol: float
    static: Contacts | None = None
    counts: Counts = field(default_factory=Counts)
    timings: dict = field(default_factory=dict)
    backend: str = ""
    device: str = ""
    dtype: str = ""

    def __len__(self):
        return len(self.hit)

    def pairs(self) -> np.ndarray:
        """[n_hit, 2]: (slave node id, master face id) of every node that hits."""
        h = np.asarray(self.hit)
        return np.stack([np.asarray(self.slave_ids)[h], np.asarray(self.face)[h]], -1)
