"""Jitted detection: the stages of arraycontact._detect.run_stages on jax.numpy.

Shapes are static: every variable-length buffer (node pairs, face pairs, candidates, attached
faces) has a capacity chosen on the host. The kernel reports the true counts; when one exceeds
its capacity the one-shot driver grows the capacity and runs again, so nothing is dropped.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from arraycontact import _grid
from arraycontact._detect import build_grids, master_arrays, run_stages, scalars

GROWTH = 1.25


@partial(jax.jit, static_argnames=("st", "capacity"))
def _kernel(sc, m, slave_x, *, st, capacity):
    grids = build_grids(jnp, st, sc, m)
    out, counts = run_stages(jnp, st, sc, m, grids, slave_x, dict(capacity))
    return out, counts


def _estimate(slave_x, m, sc, st):
    """Upper-bound pair counts from the stencil cell counts on the host (no pairs built)."""
    grids = build_grids(np, st, sc, m)
    reach = np.full(len(slave_x), sc["d_max"])
    cnt, _ = _grid.stencil_counts(np, grids["node"], slave_x, sc["node_cell"], st.node_table,
                                  reach)
    cap = {"node_pairs": int(cnt.sum())}
    if st.mode == "exact":
        reach = reach + sc["r_max"] + sc["slack"]
        cnt, _ = _grid.stencil_counts(np, grids["face"], slave_x, sc["face_cell"],
                                      st.face_table, reach)
        cap["face_pairs"] = int(cnt.sum())
        cap["candidates"] = max(cap["face_pairs"] // 4, len(slave_x))
    else:
        deg = np.diff(m["nf_offsets"])
        cap["attached"] = int(len(slave_x) * max(int(deg.max()), 1))
    return cap


def run_one_shot(slave_x, master, prep, st, dtype):
    """Plan on the host, run jitted, re-plan and re-run on overflow. Host arrays out."""
    x64 = np.dtype(dtype) == np.float64
    with jax.enable_x64(x64):
        m = master_arrays(master, prep, dtype)
        sc = scalars(prep, master, dtype)
        x = (slave_x[prep.slave_rows] - prep.origin).astype(dtype)
        est = _estimate(x, m, sc, st)
        cap = {k: max(int(np.ceil(v * GROWTH)), 1) for k, v in est.items()}
        m_dev = {k: jnp.asarray(v) for k, v in m.items()}
        sc_dev = {k: jnp.asarray(v, dtype=dtype) for k, v in sc.items()}
        x_dev = jnp.asarray(x)
        for _ in range(4):
            out, counts = _kernel(sc_dev, m_dev, x_dev, st=st, capacity=tuple(sorted(cap.items())))
            counts = {k: int(v) for k, v in counts.items()}
            over = {k: v for k, v in counts.items() if v > cap[k]}
            if not over:
                break
            cap.update({k: int(np.ceil(v * GROWTH)) for k, v in over.items()})
        out = {k: np.asarray(v) for k, v in out.items()}
    return out, counts, cap
