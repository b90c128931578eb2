"""The first detect after a Warp plan against the steady state (issue 20: "first detect after
the plan, kernel cache warm, at most 3x the steady state"), with many plans a scene so that
the medians are not one plan's luck. Each plan of the scene (a Surface new to it, as the
suite's): the plan, its first detect on wp.arrays, the steady state (a graph replay) and a
detect on buffers new to the plan (launched one by one).

    python benchmarks/first_detect.py --scenes ball_block_100 tyre [--log2 20] [--plans 4]
        [--code DIR] [--tag NAME] [--run ID] [--out DIR]
    python benchmarks/first_detect.py --table MACHINE RUN [RUN ...]   # medians of records

--code: a folder holding another commit's arraycontact/ and backends/ to import instead of
this checkout's, for an A/B in one call (run it alternately with each tree; --tag names the
side, ARRAYCONTACT_COMMIT the tree's commit for the record). One record per plan to
results/first_detect_<machine>.jsonl.
"""

import argparse
import statistics
import sys
import time
from pathlib import Path

HERE = Path(__file__).parent
sys.path[:0] = [str(HERE.parent), str(HERE.parent / "backends"), str(HERE)]
import _records  # noqa: E402


def run(a):
    import arraycontact_warp as acw
    import numpy as np
    import warp as wp
    from suite import _median_time, suite

    import arraycontact as ac
    from arraycontact._backends import quiet_warp

    quiet_warp()
    dev = "cuda"
    for element in ("tri3", "quad4"):  # the kernels compiled and loaded first
        small = ac.scenes.rough_surfaces(2**10, element=element)
        p = acw.plan(small.master, small.slave, device=dev)
        acw.detect(p, small.slave, small.master.points)
    wp.synchronize_device(dev)
    sync = lambda: wp.synchronize_device(dev)  # noqa: E731
    meta = _records.meta(a.run)
    for label, make, f in suite(a.log2):
        if label not in a.scenes:
            continue
        scene = make()
        d_max = f * scene.master.longest_edge
        m = scene.master
        for k in range(a.plans):
            fresh = ac.Surface(m.points, m.faces, m.element.name)
            t0 = time.perf_counter()
            p = acw.plan(fresh, scene.slave, d_max=d_max, device=dev)
            sync()
            plan_s = time.perf_counter() - t0
            xs = wp.array((scene.slave - p.origin).astype(np.float32), dtype=wp.vec3, device=dev)
            xm = wp.array((m.points - p.origin).astype(np.float32), dtype=wp.vec3, device=dev)
            p.origin = np.zeros(3)
            sync()
            t0 = time.perf_counter()
            acw.detect(p, xs, xm)
            sync()
            first_s = time.perf_counter() - t0
            steady_s = _median_time(lambda: acw.detect(p, xs, xm), 10, sync)
            new = iter([(wp.clone(xs), wp.clone(xm)) for _ in range(11)])
            new_s = _median_time(lambda: acw.detect(p, *next(new)), 10, sync)
            rec = dict(
                tag=a.tag,
                scene=label,
                plan=k,
                device=wp.get_device(dev).name,
                plan_s=plan_s,
                first_s=first_s,
                steady_s=steady_s,
                new_buffers_s=new_s,
            )
            _records.append("first_detect", rec, meta, a.out)
            print(rec, flush=True)


def table(machine, runs):
    rows = [r for r in _records.load("first_detect", machine) if r["run"] in runs]
    cols = ["run", "commit", "scene", "plans", "plan", "first detect", "steady", "new buffers"]
    print("| " + " | ".join([*cols, "first / steady"]) + " |")
    print("|---" * (len(cols) + 1) + "|")
    groups = {}
    for r in rows:
        groups.setdefault((r["run"], r["commit"], r["scene"]), []).append(r)
    for (run_id, commit, scene), g in groups.items():
        med = {k: statistics.median(r[k] for r in g) for k in ("plan_s", "first_s", "steady_s")}
        new = statistics.median(r["new_buffers_s"] for r in g)
        ratio = statistics.median(r["first_s"] / r["steady_s"] for r in g)
        print(
            f"| {run_id} | {commit} | {scene} | {len(g)} | {med['plan_s'] * 1e3:.1f} ms "
            f"| {med['first_s'] * 1e3:.2f} ms | {med['steady_s'] * 1e3:.2f} ms "
            f"| {new * 1e3:.2f} ms | {ratio:.2f} |"
        )


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", nargs="*", default=["ball_block_100", "ball_block_300", "tyre"])
    ap.add_argument("--log2", type=int, default=20)
    ap.add_argument("--plans", type=int, default=4)
    ap.add_argument("--code", help="a folder with another commit's arraycontact/ and backends/")
    ap.add_argument("--tag", default="")
    ap.add_argument("--run")
    ap.add_argument("--out")
    ap.add_argument("--table", nargs="+", metavar=("MACHINE", "RUN"))
    a = ap.parse_args()
    if a.table:
        return table(a.table[0], a.table[1:])
    if a.code:
        sys.path[:0] = [a.code, str(Path(a.code) / "backends")]
    run(a)


if __name__ == "__main__":
    main()
