"""Swept detection's detailed check in JAX: the certified search of arraycontact._sweep (read
its docstring) in lock step over all candidate pairs (one `lax.while_loop`, a stack of pending
boxes a pair), and the differentiable impact by the implicit-function theorem.

The search decides (under stop_gradient) which face a node hits and gives a conservative toi.
Then F(xi, eta, t) = x_face(xi, eta, t) - x_node(t) = 0 is solved by Newton from the contact
box's centre, and one more Newton step is taken with the Jacobian held constant:
z = z* - J^-1 F(z*; coordinates). Its value is z* (F(z*) = 0) and its derivative the
theorem's, dz = -J^-1 dF, so toi, xi and the impact point follow both configurations; the
values reported stay the search's (toi never late)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from arraycontact._elements import interpolate, shape_functions
from arraycontact._sweep import (
    CONTRACTIONS,
    DEPTH,
    T_TOL,
    VISITS,
    control_points,
    corner_shift,
    examine,
    krawczyk,
    natural,
    outside,
    pair_frame,
    shifted,
    unshifted,
)
from arraycontact._sweep import impact as swept_impact

#: The search goes on with the pairs still searching alone, gathered into 1/SHRINK of the
#: lanes, once no more of them are busy (and the batch has at least MIN_LANES lanes): a few
#: pairs take hundreds of boxes where most take a few, and every lane of a lock step costs.
#: A GPU steps 1024 lanes in about the time of one; a CPU steps them one by one (the graded
#: float32 test: 21 s at 1024 lanes, 0.4 s at 32, its 1519-box pair alone at the end).
SHRINK = 8
MIN_LANES = {"gpu": 1024, "cpu": 32}


def roots(element, xe0, xe1, p0, p1, valid):
    """arraycontact._sweep.roots for P pairs (valid [P]: the pairs that exist). Returns toi
    [P] (inf: none), the contact box's centre (s, w) [P, 2], converged [P], visits [P]."""
    dt = np.dtype(xe0.dtype)
    P = p0.shape[0]
    tri = element.kind == "tri"
    if tri:  # (s, w) from the corner with the most nearly orthogonal edges (corner_shift)
        r = corner_shift(xe0, jnp)
        xe0, xe1 = shifted(xe0, r, jnp), shifted(xe1, r, jnp)
    inputs = pair_frame(element, xe0, xe1, p0, p1, jnp)
    root = jnp.asarray([0, 1, 0, 1, 0, 1], dt)
    stack = jnp.zeros((P, DEPTH, 6), dt).at[:, 0].set(root)
    inf = jnp.asarray(jnp.inf, dt)
    state = (
        stack,
        valid.astype(jnp.int32),
        jnp.full(P, inf),
        jnp.full((P, 2), 0.5, dt),
        jnp.zeros(P, jnp.int32),
        jnp.ones(P, bool),
    )
    stack, sp, best, where, visits, conv = _run(element, state, inputs, T_TOL[dt])
    if tri:
        where = unshifted(where, r, jnp)
    return best, where, conv, visits


def _run(element, state, inputs, t_tol):
    """Steps until no more than 1/SHRINK of the lanes are busy, then the busy pairs on their
    own (recursively), put back in their rows. Each pair's steps are the same either way."""
    size = state[1].shape[0]
    m = size // SHRINK
    until = m if m >= MIN_LANES["cpu" if jax.default_backend() == "cpu" else "gpu"] else 0

    def busy(st):
        b = st[1] > 0
        return jnp.any(b) & (jnp.sum(b, dtype=jnp.int32) > until)

    state = jax.lax.while_loop(busy, lambda st: _step(element, st, inputs, t_tol), state)
    if not until:
        return state
    rows = jnp.nonzero(state[1] > 0, size=m, fill_value=size)[0]
    at = jnp.minimum(rows, size - 1)
    sub = jax.tree.map(lambda a: a[at], state)
    sub = sub[:1] + (jnp.where(rows < size, sub[1], 0),) + sub[2:]  # the spare lanes: done
    sub = _run(element, sub, jax.tree.map(lambda a: a[at], inputs), t_tol)
    return jax.tree.map(lambda a, b: a.at[rows].set(b, mode="drop"), state, sub)


def _step(element, state, inputs, t_tol):
    """One box of every busy pair: arraycontact._sweep.roots' loop body."""
    xa, va, p, v, dirs, margin, delta = inputs
    stack, sp, best, where, visits, conv = state
    P = sp.shape[0]
    ar = jnp.arange(P)
    inf = jnp.asarray(jnp.inf, best.dtype)
    active = sp > 0
    top = jnp.maximum(sp - 1, 0)
    box = stack[ar, top]
    visits = visits + active.astype(jnp.int32)
    live = active & (box[:, 4] < best)
    cp = control_points(element, xa, va, p, v, box, jnp)
    out, extent, spread = examine(cp, dirs, margin, jnp)
    empty, inside, kbox, within = krawczyk(element, xa, va, p, v, box, cp, margin, jnp)
    out = out | empty | outside(element, box)
    proven = ~out & inside

    def more(c):
        _, kb, kin, gone = c
        return proven & ~gone & ((kb[:, 5] - kb[:, 4] > t_tol) | ~kin)

    def contract(c):
        i, kb, kin, gone = c
        kc = control_points(element, xa, va, p, v, kb, jnp)
        em2, _, kb2, in2 = krawczyk(element, xa, va, p, v, kb, kc, margin, jnp)
        m = more(c)
        return i + 1, jnp.where(m[:, None], kb2, kb), jnp.where(m, in2, kin), gone | (m & em2)

    # Until no proven box needs more (most steps prove none), at most CONTRACTIONS times.
    _, kbox, _, gone = jax.lax.while_loop(
        lambda c: (c[0] < CONTRACTIONS) & jnp.any(more(c)),
        contract,
        (0, kbox, within, jnp.zeros_like(proven)),
    )
    out = out | (proven & gone)
    proven = proven & ~out
    box = jnp.where(proven[:, None], kbox, box)
    small = extent <= delta
    leaf = live & ~out & ((small & (box[:, 5] - box[:, 4] <= t_tol)) | proven)
    full = live & ~out & ~leaf & (top + 2 > DEPTH)
    hit = leaf | full
    conv = conv & ~full
    best = jnp.where(hit, box[:, 4], best)
    centre = 0.5 * (box[:, jnp.array([0, 2])] + box[:, jnp.array([1, 3])])
    where = jnp.where(hit[:, None], centre, where)
    split = live & ~out & ~hit
    axis = jnp.where(small, 2, jnp.argmax(spread, -1).astype(jnp.int32))
    lo_c, hi_c = 2 * axis, 2 * axis + 1
    mid = 0.5 * (box[ar, lo_c] + box[ar, hi_c])
    cols = jnp.arange(6, dtype=jnp.int32)[None, :]
    early = jnp.where(cols == hi_c[:, None], mid[:, None], box)
    late = jnp.where(cols == lo_c[:, None], mid[:, None], box)
    s1 = jnp.minimum(top + 1, DEPTH - 1)
    stack = stack.at[ar, top].set(jnp.where(split[:, None], late, stack[ar, top]))
    stack = stack.at[ar, s1].set(jnp.where(split[:, None], early, stack[ar, s1]))
    sp = jnp.where(active, top + 2 * split.astype(jnp.int32), sp)
    over = (visits > VISITS) & (sp > 0)

    def budget(args):
        # Over budget: the earliest pending box (never late), then stop. (Rare: a branch, so
        # that a step does not read every pair's whole stack.)
        best, where, conv, sp = args
        pend = jnp.where(
            jnp.arange(DEPTH, dtype=jnp.int32)[None, :] < sp[:, None], stack[:, :, 4], inf
        )
        j = jnp.argmin(pend, 1)
        b = stack[ar, j]
        earlier = over & (b[:, 4] < best)
        best = jnp.where(earlier, b[:, 4], best)
        where = jnp.where(
            earlier[:, None], 0.5 * (b[:, jnp.array([0, 2])] + b[:, jnp.array([1, 3])]), where
        )
        return best, where, conv & ~over, jnp.where(over, 0, sp)

    best, where, conv, sp = jax.lax.cond(
        jnp.any(over), budget, lambda a: a, (best, where, conv, sp)
    )
    return stack, sp, best, where, visits, conv


def _residual(element, z, xe0, xe1, p0, p1):
    """F(xi, eta, t) = x_face - x_node at time t and its Jacobian [..., 3, 3]."""
    t = z[..., 2]
    xe = xe0 + t[..., None, None] * (xe1 - xe0)
    x, dx = interpolate(element, xe, z[..., :2], jnp)
    n = shape_functions(element, z[..., :2], jnp)
    vface = jnp.sum(n[..., :, None] * (xe1 - xe0), -2)
    f = x - (p0 + t[..., None] * (p1 - p0))
    jac = jnp.concatenate([dx, (vface - (p1 - p0))[..., None]], -1)
    return f, jac


def impact(element, xe0, xe1, p0, p1, toi, s_w, iterations=12):
    """Differentiable toi, xi, point, normal and normal velocity of the chosen pairs, valued
    at the search's answer (toi, the box centre s_w) with the theorem's derivatives."""
    sg = jax.lax.stop_gradient
    xi0 = natural(element, s_w[:, 0], s_w[:, 1], jnp)
    z0 = jnp.concatenate([xi0, toi[:, None]], -1)
    a0, a1, b0, b1 = sg(xe0), sg(xe1), sg(p0), sg(p1)

    def newton(_, z):
        f, jac = _residual(element, z, a0, a1, b0, b1)
        step = jnp.linalg.solve(jac + 1e-30 * jnp.eye(3, dtype=z.dtype)[None], f[..., None])[..., 0]
        return jnp.where(jnp.all(jnp.isfinite(step), -1, keepdims=True), z - step, z)

    zs = sg(jax.lax.fori_loop(0, iterations, newton, sg(z0)))
    f, _ = _residual(element, zs, xe0, xe1, p0, p1)
    _, jac = _residual(element, zs, a0, a1, b0, b1)
    dz = jnp.linalg.solve(sg(jac) + 1e-30 * jnp.eye(3, dtype=zs.dtype)[None], f[..., None])[..., 0]
    z = zs - dz
    t = sg(toi) + (z[:, 2] - sg(z[:, 2]))
    xi = sg(xi0) + (z[:, :2] - sg(z[:, :2]))
    point, normal, vn = swept_impact(element, xe0, xe1, p0, p1, t, xi, jnp)
    return t, xi, point, normal, vn
