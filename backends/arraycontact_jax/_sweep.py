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
    examine,
    krawczyk,
    natural,
    outside,
    pair_frame,
    straddles,
)
from arraycontact._sweep import impact as swept_impact


def roots(element, xe0, xe1, p0, p1, valid):
    """arraycontact._sweep.roots for P pairs (valid [P]: the pairs that exist). Returns toi
    [P] (inf: none), the contact box's centre (s, w) [P, 2], converged [P], visits [P]."""
    dt = np.dtype(xe0.dtype)
    P = p0.shape[0]
    xa, va, p, v, dirs, margin, delta = pair_frame(element, xe0, xe1, p0, p1, jnp)
    t_tol = T_TOL[dt]
    ar = jnp.arange(P)
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

    def body(state):
        stack, sp, best, where, visits, conv = state
        active = sp > 0
        top = jnp.maximum(sp - 1, 0)
        box = stack[ar, top]
        visits = visits + active.astype(jnp.int32)
        live = active & (box[:, 4] < best)
        cp = control_points(element, xa, va, p, v, box, jnp)
        out, extent, spread = examine(cp, dirs, margin, jnp)
        empty, inside, kbox = krawczyk(element, xa, va, p, v, box, cp, margin, jnp)
        out = out | empty | outside(element, box)
        proven = ~out & inside

        def contract(_, kb):
            more = (kb[:, 5] - kb[:, 4] > t_tol) | straddles(element, kb)
            kc = control_points(element, xa, va, p, v, kb, jnp)
            kb2 = krawczyk(element, xa, va, p, v, kb, kc, margin, jnp)[2]
            return jnp.where((proven & more)[:, None], kb2, kb)

        kbox = jax.lax.fori_loop(0, CONTRACTIONS, contract, kbox)
        out = out | (proven & outside(element, kbox))
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
        # Over budget: the earliest pending box (never late), then stop.
        over = (visits > VISITS) & (sp > 0)
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
        conv = conv & ~over
        sp = jnp.where(over, 0, sp)
        return stack, sp, best, where, visits, conv

    stack, sp, best, where, visits, conv = jax.lax.while_loop(
        lambda s: jnp.any(s[1] > 0), body, state
    )
    return best, where, conv, visits


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
