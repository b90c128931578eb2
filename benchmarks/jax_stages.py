"""Where a JAX detection's time goes (`search="jax"`, no Warp), per scene of the suite: the
steady time of jitted programs that stop after each stage (the master's geometry and the
trees; then the closest-node scan; then the face scan; the whole detection), and the scans'
steps. Differences between consecutive rows are the stages' times.

    python benchmarks/jax_stages.py --log2 20 --only uniform graded_1000
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from suite import suite  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--log2", type=int, default=20)
    ap.add_argument("--only", nargs="*")
    ap.add_argument("--repeats", type=int, default=10)
    a = ap.parse_args()
    import arraycontact_jax as acj
    import jax
    import jax.numpy as jnp
    from arraycontact_jax import _grid
    from arraycontact_jax._detect import build_grids, master_geometry

    for label, make, f in suite(a.log2):
        if a.only and not any(label.startswith(o) for o in a.only):
            continue
        scene = make()
        p = acj.plan(
            scene.master, scene.slave, d_max=f * scene.master.longest_edge, dtype=np.float32,
            search="jax",
        )  # fmt: skip
        st, sc, cap = p.static, p.constants, dict(p.capacity)
        origin = np.asarray(p.origin)
        xs = jnp.asarray((scene.slave - origin).astype(np.float32))
        xm = jnp.asarray((scene.master.points - origin).astype(np.float32))

        def upto(stage):
            def run(topo, xs, xm):
                m = master_geometry(jnp, st.element, topo, xm)
                g = build_grids(jnp, st, m)
                if stage == "trees":
                    return g.node.lo[0], g.face.lo[0]
                node, dn, c = _grid.closest_node(
                    jnp, g.node, m.nodes_x, xs, d_max=sc.d_max, tie=sc.tie, slack=sc.slack
                )
                if stage == "node scan":
                    return node, dn, c
                rho = jnp.minimum(dn, sc.d_max) + sc.slack
                return _grid.candidate_faces(jnp, g.face, xs, rho, slack=sc.slack, capacity=cap)

            return jax.jit(run)

        rows = []
        for stage in ("trees", "node scan", "face scan"):
            fn = upto(stage)
            out = jax.block_until_ready(fn(p.topology, xs, xm))
            rows.append((stage, _time(lambda: fn(p.topology, xs, xm), a.repeats), out))
        rows.append(("detect", _time(lambda: acj.detect(p, xs, xm), a.repeats), None))
        steps = {k: int(v) for k, v in rows[2][2][3].items()}
        print(f"{label}: {scene.master.n_faces} faces, {len(scene.slave)} slaves, {cap}, {steps}")
        for stage, t, _ in rows:
            print(f"  up to {stage:10s} {t * 1e3:8.2f} ms")


def _time(fn, repeats):
    import jax

    jax.block_until_ready(fn())
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        ts.append(time.perf_counter() - t)
    return float(np.median(ts))


if __name__ == "__main__":
    main()
