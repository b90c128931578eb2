"""Seed 003 section 5: the single-element study (5.1, Figs. 4 and 6) and the rough layers (5.2).

    python benchmarks/seed003_study.py            # writes benchmarks/seed003/*.png and STUDY.md

5.1: a 100 x 100 lattice of points on the plane of one element (tri3, quad4: [-2, 2]^2; tri6,
quad8: [-6, 6]^2; the 3-D case of Fig. 6: tri3 with its right nodes lifted to z = 1 and the
lattice on z = 2 over [-4, 4]^2), the closest point by the active-set and the SQP methods from
starts I (closest of corners and centre) and II (centre); mean iterations, convergence, and
the share of points where the local solution is not the global one (against the reference).
One iteration-count map per element (PNG), like Fig. 4.

5.2: two interpenetrating rough layers (linear tri3 and quadratic tri6). Every candidate pair
of the exact detection is one distance computation; time per distance for the Voronoi closed
form, the brute-force projection-plus-edges method (the reference's) and the optimisation
(SQP), batched in NumPy on this CPU, as ratios to the Voronoi time beside the paper's.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

import arraycontact as ac
from arraycontact._closest_node import closest_node
from arraycontact._detect import Static, build_grids, master_arrays, scalars
from arraycontact._elements import shape_functions
from arraycontact._geometry import (
    closest_point_face,
    closest_point_triangle,
    start_option_one,
    start_option_two,
)
from arraycontact._prepare import prepare
from arraycontact._projection import candidate_faces
from arraycontact.reference import _closest_on_faces

OUT = Path(__file__).parent / "seed003"
PAPER = {"tri3": (1.6, 2.8), "quad4": (2.4, 4.7), "tri6": (1.8, 3.2), "quad8": (1.7, 3.0)}
PAPER_ACTIVE_SET = {"tri6": "1.7", "quad8": "1.7"}  # Fig. 5(c), (d); not given for linear ones
TOL = 1e-12


def lattice_study(element, lift=None):
    surface, q = ac.scenes.single_element_study(element, lift=lift)
    e = surface.element
    xe = np.broadcast_to(
        surface.points[surface.faces[0]], (len(q),) + surface.points[surface.faces[0]].shape
    )
    ref = ac.reference.closest_points(q, surface)
    L = surface.longest_edge
    rows, maps = {}, {}
    for method in ("sqp", "active_set"):
        for name, start in (("I", start_option_one), ("II", start_option_two)):
            xi, feat, loc, conv, it, kkt = closest_point_face(
                e, q, xe, start(e, q, xe), iterations=40, tol=TOL, method=method
            )
            d = np.linalg.norm(shape_functions(e, xi) @ xe[0] - q, axis=1)
            rows[method, name] = dict(
                iterations=float(it.mean()),
                converged=float(conv.mean()),
                not_global=float((d - ref.distance > 1e-10 * L).mean()),
            )
            maps[method, name] = it.reshape(100, 100)
    return surface, q, rows, maps


def plot_map(path, surface, q, it, title):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    e = surface.element
    x = q[:, 0].reshape(100, 100)
    y = q[:, 1].reshape(100, 100)
    fig, ax = plt.subplots(figsize=(5.2, 4.4))
    m = ax.pcolormesh(x, y, it, cmap="viridis", shading="nearest")
    fig.colorbar(m, label="iterations")
    # The element's edges (mapped natural-coordinate lines), dashed like Fig. 4.
    t = np.linspace(0, 1, 60)
    for a, b, *_ in e.edge_nodes:
        xi = e.nodes[a] + t[:, None] * (e.nodes[b] - e.nodes[a])
        xy = shape_functions(e, xi) @ surface.points[surface.faces[0]]
        ax.plot(xy[:, 0], xy[:, 1], "w--", lw=1)
    ax.set_aspect("equal")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _pairs(scene):
    """Candidate pairs (slave, face) of the exact detection: the distance computations."""
    master = scene.master
    prep = prepare(scene.slave, master, master.longest_edge)
    st = Static(master.element.name, "exact", prep.node_levels, prep.face_levels, 20, False)
    m = master_arrays(master, prep, np.float64)
    sc = scalars(prep, master, np.float64)
    x = scene.slave[prep.slave_rows]
    grids = build_grids(np, st, m)
    _, dn, _ = closest_node(
        np,
        grids.node,
        m.nodes_x,
        x,
        d_max=sc.d_max,
        tie=sc.tie,
        slack=sc.slack,
        capacity=None,
    )
    rho = np.minimum(dn, sc.d_max) + sc.slack
    slave, face, ok, _ = candidate_faces(np, grids.face, x, rho, slack=sc.slack, capacity=None)
    return x[slave], master.points[master.faces[face]], len(x)


def _best(fn, repeats=5):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def rough_layers_study(log2n=14):
    out = {}
    for quadratic in (False, True):
        scene = ac.scenes.rough_layers(2**log2n, quadratic=quadratic)
        r, xe, n_slaves = _pairs(scene)
        e = scene.master.element
        n = len(r)
        rec = dict(element=e.name, slaves=n_slaves, distance_computations=n, per_slave=n / n_slaves)
        xi0 = start_option_one(e, r, xe)
        res = closest_point_face(e, r, xe, xi0, iterations=20, tol=TOL, method="sqp")
        # Static shapes run the whole budget on every pair: time it with the smallest budget
        # that every pair needed.
        budget = int(res[4].max())
        sqp = _best(
            lambda: closest_point_face(e, r, xe, xi0, iterations=budget, tol=TOL, method="sqp"), 3
        )
        rec.update(
            sqp_us=sqp / n * 1e6,
            sqp_iterations=float(res[4].mean()),
            sqp_budget=budget,
            sqp_converged=float(res[3].mean()),
        )
        if not quadratic:
            rec["voronoi_us"] = (
                _best(lambda: closest_point_triangle(r, xe[:, 0], xe[:, 1], xe[:, 2])) / n * 1e6
            )
            rec["brute_force_us"] = _best(lambda: _closest_on_faces(e, r, xe)) / n * 1e6
        out[e.name] = rec
    return out


def main():
    OUT.mkdir(exist_ok=True)
    lines = [
        "# Seed 003 studies, reproduced",
        "",
        "Remade by `python benchmarks/seed003_study.py` (CPU, NumPy, float64, KKT "
        f"tolerance {TOL:g} in natural coordinates; iterations count derivative "
        "evaluations up to the first that meets the KKT conditions, so a start at the "
        "solution counts 1).",
        "",
        "## 5.1 Single element, 100 x 100 lattice (Fig. 4)",
        "",
        "| element | paper SQP I / II | SQP I / II | paper active set | active set I / II "
        "| converged | local, not global (I) |",
        "|---|---|---|---|---|---|---|",
    ]
    for element in ("tri3", "quad4", "tri6", "quad8"):
        surface, q, rows, maps = lattice_study(element)
        p = PAPER[element]
        s1, s2 = rows["sqp", "I"], rows["sqp", "II"]
        a1, a2 = rows["active_set", "I"], rows["active_set", "II"]
        conv = min(v["converged"] for v in rows.values())
        lines.append(
            f"| {element} | {p[0]} / {p[1]} | {s1['iterations']:.2f} / "
            f"{s2['iterations']:.2f} | {PAPER_ACTIVE_SET.get(element, '-')} | "
            f"{a1['iterations']:.2f} / {a2['iterations']:.2f} "
            f"| {conv:.2%} | {s1['not_global']:.2%} |"
        )
        plot_map(
            OUT / f"fig4_{element}.png",
            surface,
            q,
            maps["sqp", "I"],
            f"{element}: SQP iterations, start I (mean {s1['iterations']:.2f})",
        )
        print(lines[-1], flush=True)
    lines += [
        "",
        "Geometries (`arraycontact.scenes.STUDY_ELEMENTS`): the paper gives none in numbers; "
        "ours are curved like Fig. 4, with the right edge convex and the others concave "
        'on quad8 (the paper: convex edges add normal-projection regions, "as shown by '
        'the right edges of both elements"); tri6 has its right and left edges convex. '
        "With quad8's top edge convex too (our first geometry) SQP start I takes 1.74 "
        "iterations, active set 1.76. What brought the counts down: the exact closest "
        "point on a curved edge in one iteration (the roots of a cubic, "
        "`closest_point_edge`) and the second-order (Chebyshev) correction of the free "
        "Newton step, which makes interior points converge cubically.",
    ]
    surface, q, rows, maps = lattice_study("tri3", lift=1.0)
    s1, s2 = rows["sqp", "I"], rows["sqp", "II"]
    lines += [
        "",
        "3-D case (Fig. 6: tri3 with its right nodes at z = 1, lattice on z = 2): "
        f"SQP {s1['iterations']:.2f} / {s2['iterations']:.2f} iterations (I / II), "
        f"active set {rows['active_set', 'I']['iterations']:.2f} / "
        f"{rows['active_set', 'II']['iterations']:.2f}, converged "
        f"{min(v['converged'] for v in rows.values()):.2%}.",
    ]
    plot_map(
        OUT / "fig6_tri3_3d.png",
        surface,
        q,
        maps["sqp", "I"],
        f"tri3 in 3-D: SQP iterations, start I (mean {s1['iterations']:.2f})",
    )
    print(lines[-1], flush=True)
    rl = rough_layers_study()
    lin, quad = rl["tri3"], rl["tri6"]
    v = lin["voronoi_us"]
    lines += [
        "",
        "## 5.2 Interpenetrating rough layers",
        "",
        "| | slaves | distance computations (per slave) | Voronoi | projection + edges | "
        "SQP | SQP iterations |",
        "|---|---|---|---|---|---|---|",
        "| paper, linear | 20,589 | 161,450 (7.8) | 0.18 us (1) | 0.7 us (3.9) | "
        "10.8 us (60) | 4.6 |",
        f"| ours, tri3 | {lin['slaves']} | {lin['distance_computations']} "
        f"({lin['per_slave']:.1f}) | {v:.3f} us (1) | {lin['brute_force_us']:.3f} us "
        f"({lin['brute_force_us'] / v:.1f}) | {lin['sqp_us']:.3f} us "
        f"({lin['sqp_us'] / v:.1f}) | {lin['sqp_iterations']:.2f} |",
        "| paper, quadratic | 76,052 | 628,017 (8.3) | | | 12.3 us (68) | 5 |",
        f"| ours, tri6 | {quad['slaves']} | {quad['distance_computations']} "
        f"({quad['per_slave']:.1f}) | | | {quad['sqp_us']:.3f} us "
        f"({quad['sqp_us'] / v:.1f}) | {quad['sqp_iterations']:.2f} |",
        "",
        "Times per distance are batched NumPy on one CPU core (all pairs at once, "
        "MATLAB per call in the paper); the ratios to the Voronoi time are the "
        "comparison. The batched SQP runs its whole iteration budget on every pair "
        "(static shapes, no early exit); it is timed with the smallest budget every pair "
        f"needed ({lin['sqp_budget']} for tri3, {quad['sqp_budget']} for tri6), so its "
        "time reflects that budget, not the mean iteration count, and each iteration "
        "includes the exact solve along every edge. SQP converged on "
        f"{lin['sqp_converged']:.2%} (tri3) and {quad['sqp_converged']:.2%} (tri6) of "
        "the pairs.",
    ]
    print("\n".join(lines[-8:]), flush=True)
    (OUT / "STUDY.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
