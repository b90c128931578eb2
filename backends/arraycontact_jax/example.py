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
    """Returns the gaps and energy before and after, whether the final contacts overflowed,
    and how many times the path outgrew the plan (then re-planned and solved again)."""
    s = scenes.rough_surfaces(n_nodes, seed=seed)
    length = s.master.longest_edge
    body = s.slave - [0.0, 0.0, sink]  # sunk into the master: deep penetration
    centre = body.mean(0)
    margin = 1e-3 * length
    p = plan(s.master, body, d_max=2 * sink, growth=2.0)
    master = jnp.asarray(s.master.points)

    def contacts(p, q):
        x = jnp.asarray(body - centre) @ rotation(q[3:]).T + (centre + q[:3])[None, :]
        return detect(p, x, master)

    def energy(p, q):
        c = contacts(p, q)
        g = jnp.where(c.active, c.gap, jnp.inf)
        return 0.5 * k * jnp.sum(jnp.minimum(g - margin, 0.0) ** 2)

    @jax.jit
    def solve(p, q):
        """Newton steps; also the largest count of every capacity met on the way."""

        def worst(q, most):
            count = contacts(p, q).counts.count
            return {key: jnp.maximum(most[key], count[key]) for key in most}

        def step(_, state):
            q, most = state
            h = jax.hessian(lambda q: energy(p, q))(q) + 1e-9 * k * jnp.eye(6)
            q = q - jnp.linalg.solve(h, jax.grad(lambda q: energy(p, q))(q))
            return q, worst(q, most)

        most = {key: jnp.int32(0) for key in dict(p.capacity)}
        return jax.lax.fori_loop(0, steps, step, (q, worst(q, most)))

    # The overflow protocol: a path that met a count above its capacity is solved again with
    # a plan sized for the largest counts it met (a step's result could be incomplete).
    q0 = jnp.zeros(6, dtype=master.dtype)
    replans = 0
    while True:
        q, most = solve(p, q0)
        most = {key: int(v) for key, v in most.items()}
        if all(most[key] <= v for key, v in p.capacity):
            break
        replans += 1
        p = plan(s.master, body, d_max=2 * sink, growth=2.0, minimum=most)

    def min_gap(q):
        c = contacts(p, q)
        return float(jnp.min(jnp.where(c.active, c.gap, jnp.inf)))

    return dict(
        min_gap_before=min_gap(q0),
        min_gap_after=min_gap(q),
        energy_before=float(energy(p, q0)),
        energy_after=float(energy(p, q)),
        motion=np.asarray(q),
        length=length,
        overflow=bool(contacts(p, q).overflow),
        replans=replans,
    )


if __name__ == "__main__":
    for key, value in push_out().items():
        print(f"{key:>15}: {value}")
