"""Warp's own queries on the same points, as peers: `wp.Mesh` BVH closest point
(`mesh_query_point_no_sign`; build + query and refit + query) and `wp.HashGrid` closest node.

Each function returns (first call s, steady s, result arrays as NumPy) for slaves `q` [n, 3]
on the master `surface` (tri3, or quads split into two triangles), with the search radius
`d_max`. Steady state is the median of `repeats` synchronised runs.
"""

from __future__ import annotations

import statistics
import time

import numpy as np
import warp as wp


@wp.kernel
def _mesh_query(
    mesh: wp.uint64,
    q: wp.array(dtype=wp.vec3),
    d_max: float,
    face_out: wp.array(dtype=int),
    dist_out: wp.array(dtype=float),
):
    i = wp.tid()
    r = wp.mesh_query_point_no_sign(mesh, q[i], d_max)
    if r.result:
        x = wp.mesh_eval_position(mesh, r.face, r.u, r.v)
        face_out[i] = r.face
        dist_out[i] = wp.length(q[i] - x)
    else:
        face_out[i] = -1
        dist_out[i] = -1.0


@wp.kernel
def _grid_query(
    grid: wp.uint64,
    q: wp.array(dtype=wp.vec3),
    nodes: wp.array(dtype=wp.vec3),
    d_max: float,
    node_out: wp.array(dtype=int),
):
    i = wp.tid()
    p = q[i]
    best = int(-1)
    best_d = d_max * d_max
    query = wp.hash_grid_query(grid, p, d_max)
    j = int(0)
    while wp.hash_grid_query_next(query, j):
        d = wp.length_sq(nodes[j] - p)
        if d <= best_d:
            best_d = d
            best = j
    node_out[i] = best


def timed(fn, repeats, device):
    """(first call s, median of `repeats` synchronised calls s)."""
    t0 = time.perf_counter()
    fn()
    wp.synchronize_device(device)
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        wp.synchronize_device(device)
        times.append(time.perf_counter() - t0)
    return first, statistics.median(times)


def alternating(calls, repeats, device):
    """The median time of each call, timed in turn (a shared machine's load changes over a
    run: in turn, both calls see the same)."""
    times = [[] for _ in calls]
    for _ in range(repeats):
        for c, t in zip(calls, times):
            t0 = time.perf_counter()
            c()
            wp.synchronize_device(device)
            t.append(time.perf_counter() - t0)
    return [statistics.median(t) for t in times]


def _triangles(surface):
    f = surface.faces
    if surface.element.name == "quad4":
        f = np.concatenate([f[:, [0, 1, 2]], f[:, [0, 2, 3]]])
    elif surface.element.name != "tri3":
        raise ValueError("the Warp mesh peers take tri3 or quad4 masters")
    return f.astype(np.int32).reshape(-1)


def mesh_peers(surface, q, d_max, repeats=10, device="cuda"):
    """BVH build + query, and refit + query (the BVH of a moving master)."""
    pts = wp.array(surface.points.astype(np.float32), dtype=wp.vec3, device=device)
    idx = wp.array(_triangles(surface), dtype=int, device=device)
    qa = wp.array(q.astype(np.float32), dtype=wp.vec3, device=device)
    face = wp.empty(len(q), dtype=int, device=device)
    dist = wp.empty(len(q), dtype=float, device=device)
    holder = {}

    def build_query():
        holder["mesh"] = wp.Mesh(points=pts, indices=idx)
        wp.launch(
            _mesh_query,
            len(q),
            inputs=[holder["mesh"].id, qa, float(d_max)],
            outputs=[face, dist],
            device=device,
        )

    def refit_query():
        holder["mesh"].refit()
        wp.launch(
            _mesh_query,
            len(q),
            inputs=[holder["mesh"].id, qa, float(d_max)],
            outputs=[face, dist],
            device=device,
        )

    b = timed(build_query, repeats, device)
    r = timed(refit_query, repeats, device)
    out = dict(build_query=b, refit_query=r, face=face.numpy(), distance=dist.numpy())
    if wp.get_device(device).is_cuda:
        # Refit + query replayed as a CUDA graph, as our detect replays itself: like with like.
        with wp.ScopedCapture(device=device) as cap:
            refit_query()
        out["refit_query_graph"] = timed(lambda: wp.capture_launch(cap.graph), repeats, device)
    return out


def hashgrid_peer(surface, q, d_max, repeats=10, device="cuda"):
    """HashGrid build + closest-node query within d_max."""
    nodes = surface.points.astype(np.float32)
    na = wp.array(nodes, dtype=wp.vec3, device=device)
    qa = wp.array(q.astype(np.float32), dtype=wp.vec3, device=device)
    out = wp.empty(len(q), dtype=int, device=device)
    grid = wp.HashGrid(128, 128, 128, device=device)

    def run():
        grid.build(na, float(d_max))
        wp.launch(
            _grid_query,
            len(q),
            inputs=[grid.id, qa, na, float(d_max)],
            outputs=[out],
            device=device,
        )

    t = timed(run, repeats, device)
    return dict(build_query=t, node=out.numpy())
