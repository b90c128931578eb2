""" "Skip what a scene doesn't need", measured (issue 7): the time each skip saves, on this CPU,
NumPy float64, as ratios within one run.

    python benchmarks/skips.py            # -> results/skips_cpu.jsonl and stdout

1. Boxes that do not meet: `detect` returns before any grid; compared with the same two
   surfaces moved into contact.
2. No passing-by test on a closed master (node mode): the boundary test of eqs. (12)-(13)
   forced on for a closed sphere against the default (off).
3. No Newton for linear faces: tri3 faces through the closed form (default) against the same
   faces through the active-set Newton method of curved faces.
4. A master that does not move keeps its grid (Warp, CPU device, float32):
   `detect(plan, slaves)` against `detect(plan, slaves, master_points)`. Only the Warp back end
   has it (the NumPy and JAX calls rebuild their grids: 1-3 % of a NumPy detection).
"""

from __future__ import annotations

import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
import _records  # noqa: E402

import arraycontact as ac
from arraycontact import _detect, _projection
from arraycontact._backends import quiet_warp

HERE = Path(__file__).parent


def _time(fn, repeats=3):
    fn()
    t = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        t.append(time.perf_counter() - t0)
    return statistics.median(t)


def far_apart(n=2**16):
    s = ac.scenes.rough_surfaces(n, seed=0)
    far = s.slave + [0.0, 0.0, 1e3]
    t_far = _time(lambda: ac.detect(far, s.master))
    t_near = _time(lambda: ac.detect(s.slave, s.master))
    return dict(skip="boxes do not meet: no grid", with_skip_s=t_far, without_skip_s=t_near)


def passing_by(n=2**14):
    sphere = _sphere(n)
    rng = np.random.default_rng(0)
    d = rng.standard_normal((n, 3))
    slave = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(9.5, 10.5, (n, 1))
    d_max = _detect.default_d_max(sphere)
    prep = _detect.prepare(slave, sphere, d_max, np.float64)

    def run(flag):
        st = _detect.Static(
            element="quad4",
            mode="node",
            node_levels=prep.node_levels,
            face_levels=prep.face_levels,
            iterations=_detect.ITERATIONS["quad4"],
            passing_by=flag,
        )
        return lambda: _detect._run_numpy(slave, sphere, prep, st, np.float64)

    return dict(
        skip="closed master: no passing-by test (node mode)",
        with_skip_s=_time(run(False)),
        without_skip_s=_time(run(True)),
        closed=bool(sphere.closed),
    )


def _sphere(n):
    """A closed quad4 cube-sphere of about n nodes, radius 10, around the sphere scene."""
    k = max(int(np.sqrt(n / 6)), 2)
    g = np.linspace(-1, 1, k + 1)
    pts, faces = [], []
    for axis in range(3):
        for sign in (-1, 1):
            u, v = np.meshgrid(g, g, indexing="ij")
            p = np.zeros(u.shape + (3,))
            p[..., axis] = sign
            p[..., (axis + 1) % 3] = u
            p[..., (axis + 2) % 3] = v
            ids = np.arange(u.size).reshape(u.shape) + sum(len(q) for q in pts)
            f = np.stack([ids[:-1, :-1], ids[1:, :-1], ids[1:, 1:], ids[:-1, 1:]], -1)
            f = f.reshape(-1, 4)
            if sign * (1 if axis != 1 else 1) < 0:
                f = f[:, ::-1]
            pts.append(p.reshape(-1, 3))
            faces.append(f)
    p = np.concatenate(pts)
    f = np.concatenate(faces)
    # Merge the nodes shared by neighbouring sides.
    key = np.round(p * 1e6).astype(np.int64)
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    p = p[first]
    f = inv.reshape(-1)[f]
    p = 10.0 * p / np.linalg.norm(p, axis=1, keepdims=True)
    # Orient outward: flip faces whose normal points inward.
    c = p[f].mean(1)
    nrm = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 3]] - p[f[:, 0]])
    inward = np.einsum("ij,ij->i", nrm, c) < 0
    f[inward] = f[inward][:, ::-1]
    return ac.Surface(p, f, "quad4")


def linear_closed_form(n=2**14):
    s = ac.scenes.rough_surfaces(n, seed=1)
    t_closed = _time(lambda: ac.detect(s.slave, s.master))
    real = _projection.closest_point_triangle

    def newton_instead(p, a, b, c, xp=np):
        from arraycontact._elements import get_element
        from arraycontact._geometry import closest_point_face, start_option_one

        e = get_element("tri3")
        xe = xp.stack([a, b, c], 1)
        xi0 = start_option_one(e, p, xe, xp)
        xi, feature, local, _, _, _ = closest_point_face(
            e, p, xe, xi0, iterations=12, tol=1e-10, xp=xp
        )
        return xi, feature, local

    try:
        _projection.closest_point_triangle = newton_instead
        t_newton = _time(lambda: ac.detect(s.slave, s.master))
    finally:
        _projection.closest_point_triangle = real
    return dict(
        skip="linear faces: closed form, no Newton (tri3)",
        with_skip_s=t_closed,
        without_skip_s=t_newton,
    )


def static_master(n=2**16):
    import arraycontact_warp as acw
    import warp as wp

    quiet_warp()
    s = ac.scenes.rough_surfaces(n, seed=2)
    p = acw.plan(s.master, s.slave, device="cpu")
    xs = wp.array(s.slave.astype(np.float32), dtype=wp.vec3, device="cpu")
    xm = wp.array(s.master.points.astype(np.float32), dtype=wp.vec3, device="cpu")
    moving = _time(lambda: (acw.detect(p, xs, xm), wp.synchronize()))
    still = _time(lambda: (acw.detect(p, xs), wp.synchronize()))
    return dict(
        skip="master does not move: grid kept (warp, cpu)", with_skip_s=still, without_skip_s=moving
    )


def main():
    meta = _records.meta()
    device = "cpu: " + (platform.processor() or platform.machine())
    for fn in (far_apart, passing_by, linear_closed_form, static_master):
        r = fn()
        r["saved_fraction"] = 1 - r["with_skip_s"] / r["without_skip_s"]
        r["device"] = device
        _records.append("skips", r, meta)
        print(
            f"{r['skip']}: {r['with_skip_s'] * 1e3:.1f} ms with the skip, "
            f"{r['without_skip_s'] * 1e3:.1f} ms without ({r['saved_fraction'] * 100:.0f} % "
            f"saved)",
            flush=True,
        )


if __name__ == "__main__":
    main()
