"""Detection over several GPUs with the JAX back end's sharded plan.

    python benchmarks/sharding.py --weak-log2 20 --strong-log2 23 [--search jax|warp]
        [--run ID] [--out DIR]
    python benchmarks/sharding.py --table [--machine h200x2] [--run ID]

Records go to DIR/sharding_<machine>.jsonl (default DIR: results/; machine: e.g. h200x2).

Weak scaling: D * 2^weak nodes per surface on D = 1, 2, ... devices (the scene grows with the
devices: a wider rough square, or the graded family at a fixed ratio); strong scaling: 2^strong
nodes per surface on each D. Every run: the plan's time, the first and steady-state detection
(median of --repeats, each call waited for; and "pipelined": --repeats calls dispatched
back to back with one wait, as a simulation loop calls), the one-device plan/detect of the
same scene in the same run (the baseline of the efficiencies, and the answer the sharded rows
must equal), the time of the exchange alone (the same all_to_alls on the plan's routes, no
detection) and the balance (the plan's per-device counts). Efficiency (weak): one device's
time at 2^weak over D devices' time at D * 2^weak.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

HERE = Path(__file__).parent
sys.path[:0] = [str(HERE.parent), str(HERE.parent / "backends")]
import _records  # noqa: E402


def _scene(name, n, seed=0):
    from arraycontact import scenes

    if name == "rough":
        return scenes.rough_surfaces(n, seed=seed)
    if name == "graded":
        return scenes.graded_surfaces(n, ratio=10.0, seed=seed)
    raise ValueError(name)


WARM = 5


def _timed(f, repeats):
    import jax

    t = time.perf_counter()
    out = jax.block_until_ready(f())
    first = time.perf_counter() - t
    # Unmeasured calls first: a run's first timings came out 10-20 % slow otherwise (one GPU's
    # Warp search at 2^20: 4.28 ms first in a run, 3.52 ms after other jobs; the GPU's clocks).
    for _ in range(WARM):
        jax.block_until_ready(f())
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(f())
        times.append(time.perf_counter() - t)
    return out, first, float(np.median(times))


def _pipelined(f, repeats):
    """The mean time of `repeats` calls dispatched back to back with one wait, as a
    simulation loop calls (the host's launches overlap the devices' work; a synchronised
    call pays them: 0.5 ms on one H200, about 1 ms on two)."""
    import jax

    t = time.perf_counter()
    jax.block_until_ready([f() for _ in range(repeats)])
    return (time.perf_counter() - t) / repeats


def _exchange_only(p):
    """The sharded detection's all_to_alls on the plan's routes (the rows that cross
    devices), without the detection: one for the coordinates, one for the answers and the
    counts."""
    import jax
    import jax.numpy as jnp
    from arraycontact_jax import _shard
    from jax.sharding import PartitionSpec as P

    axis, n_dev = p.axis, p.n_devices
    dtype = jnp.dtype(p.local.dtype)

    b_s, b_m = p.blocks
    # (as detect: a side whose rows are no multiple of the devices is not exchanged, and
    # then the answers are gathered everywhere)
    everywhere, rep_m = p.replicated
    sides = [q for q, rep in (("m_", rep_m), ("s_", everywhere)) if not rep]

    def body(ex, s_blk, m_blk):
        ex = jax.tree_util.tree_map(lambda a: a[0], ex)
        blks = {"m_": m_blk, "s_": s_blk}
        got = _shard._exchange([blks[q] for q in sides], ex, sides, axis) if sides else []
        seed = sum(r[0, 0, 0] for r in got) if got else jnp.zeros((), dtype)
        cap = ex["s_take"].shape[0]
        vals = {
            "f": jnp.zeros((cap, 10), dtype) + seed,
            "i": jnp.zeros((cap, 5), jnp.int32) + seed.astype(jnp.int32),
        }
        counts = {"count": jnp.zeros(4, jnp.int32), "motion": jnp.zeros(2, dtype)}
        home = _shard._everywhere if everywhere else _shard._home
        r, _ = home(vals, ex, axis, counts)
        return (jnp.sum(r["f"]) + jnp.sum(r["i"]))[None]

    f = jax.jit(
        jax.shard_map(
            body, mesh=p.mesh, in_specs=(P(axis),) * 3, out_specs=P(axis), check_vma=False
        )
    )
    rows = jax.sharding.NamedSharding(p.mesh, P(axis))  # (as detect gets them: no resharding)
    xs = jax.device_put(jnp.zeros((n_dev * b_s, 3), dtype), rows)
    xm = jax.device_put(jnp.zeros((n_dev * b_m, 3), dtype), rows)
    return lambda: f(p.exchange, xs, xm)


def _diff(c, r):
    ints = {
        k: int((np.asarray(getattr(c, k)) != np.asarray(getattr(r, k))).sum())
        for k in ("active", "face", "feature", "master_node", "status")
    }
    floats = {
        k: float(
            np.nanmax(np.abs(np.asarray(getattr(c, k)) - np.asarray(getattr(r, k))), initial=0)
        )
        for k in ("gap", "point", "normal", "xi")
    }
    return ints, floats


def _ties(s, c, r, dtype):
    """Where the sharded face differs from one device's: the two faces' float64 distances to
    the slave, against the tie band (the smallest face id within `tie` of the smallest
    distance wins). `exact_*`: how many rows each answer agrees with exact arithmetic on
    (float64 distances, the same band, the two faces alone); `band_edge`: rows whose distance
    difference lies within 1e-3 tie of the band's edge (decided by rounding)."""
    from arraycontact._detect import TIE_RTOL
    from arraycontact.reference import _closest_on_faces

    rows = np.nonzero(np.asarray(c.face) != np.asarray(r.face))[0]
    out = {"rows": int(len(rows))}
    fa, fb = np.asarray(r.face)[rows], np.asarray(c.face)[rows]
    both = (fa >= 0) & (fb >= 0)
    rows, fa, fb = rows[both], fa[both], fb[both]
    if not len(rows):
        return out
    m = s.master
    x = s.slave[rows].astype(dtype).astype(float)  # the coordinates the detections saw
    xm = m.points.astype(dtype).astype(float)
    da = np.sqrt(_closest_on_faces(m.element, x, xm[m.faces[fa]])[1])
    db = np.sqrt(_closest_on_faces(m.element, x, xm[m.faces[fb]])[1])
    tie = TIE_RTOL[np.dtype(dtype)] * m.longest_edge
    lo_id = np.where(fa < fb, da, db)  # the smaller id wins where it is within the band
    hi_id = np.where(fa < fb, db, da)
    exact = np.where(lo_id <= hi_id + tie, np.minimum(fa, fb), np.maximum(fa, fb))
    out.update(
        tie=float(tie),
        largest_distance_difference=float(np.abs(da - db).max()),
        band_edge=int((np.abs(np.abs(da - db) - tie) < 1e-3 * tie).sum()),
        exact_one_device=int((exact == fa).sum()),
        exact_sharded=int((exact == fb).sum()),
    )
    return out


_BASELINE = {}


def run(scene_name, n, n_dev, repeats, dtype, baseline, search="jax", drop=0):
    import arraycontact_jax as acj
    import jax
    from jax.sharding import Mesh, NamedSharding
    from jax.sharding import PartitionSpec as P

    s = _scene(scene_name, n)
    if drop:  # rows that are no multiple of the devices: replicated in and out
        s = replace(s, slave=s.slave[:-drop])
    slave = jax.device_put(s.slave.astype(dtype))
    pts = jax.device_put(s.master.points.astype(dtype))
    rec = dict(scene=scene_name, nodes_per_surface=n, devices=n_dev, dtype=np.dtype(dtype).name)
    rec["search"] = search
    rec["faces"], rec["slaves"] = s.master.n_faces, len(s.slave)
    key = (scene_name, n, search, drop)
    if baseline and key in _BASELINE:  # measured in this run already
        r, one_rec = _BASELINE[key]
        rec.update(one_rec)
    elif baseline:
        t = time.perf_counter()
        one = acj.plan(s.master, s.slave, dtype=dtype, search=search)
        one_rec = {"one_device_plan_s": time.perf_counter() - t}
        r, one_rec["one_device_first_s"], one_rec["one_device_s"] = _timed(
            lambda: acj.detect(one, slave, pts), repeats
        )
        one_rec["one_device_pipelined_s"] = _pipelined(lambda: acj.detect(one, slave, pts), repeats)
        r = jax.tree.map(np.asarray, r)
        one_rec["active"] = int(r.active.sum())
        rec.update(one_rec)
        _BASELINE[key] = r, one_rec
        del one
    mesh = Mesh(np.array(jax.devices()[:n_dev]), ("space",))
    t = time.perf_counter()
    p = acj.plan(s.master, s.slave, dtype=dtype, mesh=mesh, search=search)
    rec["plan_s"] = time.perf_counter() - t
    if len(s.slave) % n_dev == 0 and len(s.master.points) % n_dev == 0:
        # As a simulator on several devices holds them: rows split over the devices.
        rows = NamedSharding(mesh, P("space"))
        slave, pts = jax.device_put(slave, rows), jax.device_put(pts, rows)
        rec["inputs"] = "sharded by rows"
    else:  # (rows JAX cannot split in equal blocks: on every device, not moved each call)
        everywhere = NamedSharding(mesh, P())
        slave, pts = jax.device_put(slave, everywhere), jax.device_put(pts, everywhere)
        rec["inputs"] = "replicated"
    c, rec["first_s"], rec["detect_s"] = _timed(lambda: acj.detect(p, slave, pts), repeats)
    rec["detect_pipelined_s"] = _pipelined(lambda: acj.detect(p, slave, pts), repeats)
    rec["overflow"] = bool(c.overflow)
    _, _, rec["exchange_s"] = _timed(_exchange_only(p), repeats)
    rec["balance"] = {k: v for k, v in p.counts}
    if p.local.search is not None:  # the CUDA graphs the parts' Warp plans hold (one each)
        rec["warp_graphs"] = sum(len(q.graph_of) for q in p.local.search.plans)
    if baseline:
        c = jax.tree.map(np.asarray, c)
        rec["mismatch"], rec["float_diff"] = _diff(c, r)
        if rec["mismatch"]["face"]:
            rec["ties"] = _ties(s, c, r, dtype)
    return rec


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--weak-log2", type=int, default=20)
    ap.add_argument("--strong-log2", type=int, default=23)
    ap.add_argument("--scenes", nargs="+", default=["rough", "graded"])
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--dtype", default="float32")
    ap.add_argument("--search", nargs="+", default=["jax"], choices=["jax", "warp"])
    ap.add_argument("--only", choices=["weak", "strong"], default=None)
    ap.add_argument(
        "--drop",
        type=int,
        default=0,
        help="slaves dropped from each scene: rows that are no multiple of the devices, which "
        "come in and go out replicated",
    )
    ap.add_argument("--out", default=None, help="folder of the records (default results/)")
    ap.add_argument("--run", default=None, help="run id recorded (--table: the run shown)")
    ap.add_argument("--table", action="store_true", help="print a run's records as a table")
    ap.add_argument("--machine", default="h200x2", help="--table: the records' machine")
    args = ap.parse_args()
    if args.table:
        return table(args.machine, args.run)
    import jax

    if np.dtype(args.dtype) == np.float64:
        jax.config.update("jax_enable_x64", True)
    devices = jax.devices()
    n_max = len(devices)
    meta = _records.meta(args.run)
    dtype = np.dtype(args.dtype)
    counts = [d for d in (1, 2, 4, 8) if d <= n_max]
    jobs = []
    if args.only in (None, "weak"):
        for name in args.scenes:
            jobs += [("weak", name, d * 2**args.weak_log2, d) for d in counts]
    if args.only in (None, "strong"):
        # One device's time is the baseline's (the same scene, unsharded).
        jobs += [("strong", args.scenes[0], 2**args.strong_log2, d) for d in counts if d > 1]
    for search in args.search:
        for kind, name, n, d in jobs:
            rec = run(name, n, d, args.repeats, dtype, True, search, args.drop)
            rec.update(kind=kind, device=devices[0].device_kind, n_visible=n_max, dropped=args.drop)
            print(json.dumps(rec), flush=True)
            _records.append("sharding", rec, meta, out=args.out, n_devices=n_max)


def _ms(v):
    return "-" if v is None else f"{v * 1e3:.2f}"


def table(machine, run=None):
    """A run's records (default: the newest run) as the markdown table of RESULTS.md."""
    recs = _records.run_of(_records.load("sharding", machine), run)
    if not recs:
        return
    r0 = recs[0]
    commands = " and ".join(f"`{c}`" for c in dict.fromkeys(r["command"] for r in recs))
    print(f"Run {r0['run']} ({r0['device']}, commit {_records.commit(r0)}): {commands}\n")
    rows = []
    for r in recs:
        b = r["balance"]
        rows.append(
            [
                r["kind"],
                r.get("search", "jax"),
                r["scene"],
                r["devices"],
                f"2^{int(np.log2(r['nodes_per_surface']))}",
                f"{r['one_device_s'] * 1e3:.2f}",
                f"{r['detect_s'] * 1e3:.2f}",
                _ms(r.get("one_device_pipelined_s")),
                _ms(r.get("detect_pipelined_s")),
                f"{r['exchange_s'] * 1e3:.2f}",
                " / ".join(str(v) for v in b["slaves"]),
                f"{r['plan_s']:.1f}",
                sum(r.get("mismatch", {}).values()),
                f"{max(r['float_diff'].values()):.1g}",
            ]
        )
    header = [
        "run", "search", "scene", "GPUs", "nodes per surface", "one device (ms)", "sharded (ms)",
        "one device, pipelined (ms)", "sharded, pipelined (ms)", "exchange (ms)",
        "slaves per GPU", "plan (s)", "integer fields differing", "largest float difference",
    ]  # fmt: skip
    print(_records.markdown(header, rows))


if __name__ == "__main__":
    main()
