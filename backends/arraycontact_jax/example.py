"""End-to-end differentiable contact: push a penetrating body out of a rough master.

The slave body (a rough surface's nodes, sunk into the master) moves rigidly: translation t and
rotation vector w about its centroid. The penalty energy

    E(t, w) = 1/2 k sum_i min(g_i - margin, 0)^2

(gap g of each active slave, a small target margin so that the minimiser separates the bodies
rather than approaching contact from inside) is minimised by damped Newton steps whose gradient
comes from `jax.grad` and Hessian from `jax.hessian`, through `arraycontact_jax.detect`, inside
one jitted `lax.fori_loop`. Run it: `python -m arraycontact_jax.example`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from arraycontact import scenes

from ._detect import detect, plan


def rotation(w):
    """Rotation matrix of the rotation vector w (Rodrigues), smooth at w = 0."""
    t2 = jnp.dot(w, w)
    small = t2 < 1e-12
    t = jnp.sqrt(jnp.where(small, 1.0, t2))
    a = jnp.where(small, 1 - t2 / 6, jnp.sin(t) / t)
    b = jnp.where(small, 0.5 - t2 / 24, (1 - jnp.cos(t)) / jnp.where(small, 1.0, t2))
    k = jnp.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    return jnp.eye(3) + a * k + b * k @ k


def push_out(n_nodes=2**12, steps=40, k=1e3, sink=1.6, seed=0):
    """Returns the gaps and energy before and after, and whether any step overflowed."""
    s = scenes.rough_surfaces(n_nodes, seed=seed)
    length = s.master.longest_edge
    body = s.slave - [0.0, 0.0, sink]  # sunk into the master: deep penetration
    centre = body.mean(0)
    margin = 1e-3 * length
    p = plan(s.master, body, d_max=2 * sink, growth=2.0)
    master = jnp.asarray(s.master.points)

    def contacts(q):
        x = (jnp.asarray(body) - centre) @ rotation(q[3:]).T + centre + q[:3]
        return detect(p, x, master)

    def energy(q):
        c = contacts(q)
        g = jnp.where(c.active, c.gap, jnp.inf)
        return 0.5 * k * jnp.sum(jnp.minimum(g - margin, 0.0) ** 2)

    @jax.jit
    def solve(q):
        def step(_, state):
            q, overflow = state
            h = jax.hessian(energy)(q) + 1e-9 * k * jnp.eye(6)
            q = q - jnp.linalg.solve(h, jax.grad(energy)(q))
            return q, overflow | contacts(q).overflow

        return jax.lax.fori_loop(0, steps, step, (q, contacts(q).overflow))

    q0 = jnp.zeros(6, dtype=master.dtype)
    q, overflow = solve(q0)

    def min_gap(q):
        c = contacts(q)
        return float(jnp.min(jnp.where(c.active, c.gap, jnp.inf)))

    return dict(min_gap_before=min_gap(q0), min_gap_after=min_gap(q), energy_before=float(
        energy(q0)), energy_after=float(energy(q)), motion=np.asarray(q), length=length,
        overflow=bool(overflow))


if __name__ == "__main__":
    for key, value in push_out().items():
        print(f"{key:>15}: {value}")
