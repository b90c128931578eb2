"""The Warp back end's first call in a new process on an empty kernel cache: what a user's
first `ac.detect(..., backend="warp")` on a new machine waits for (issue 20: "report
cold-cache compile times separately"). Each case runs in a child process of its own with a
new, empty Warp kernel cache folder and the CUDA driver's JIT cache off (CUDA_CACHE_DISABLE=1:
where Warp hands the driver PTX, the driver caches its own compilation across processes).

    python benchmarks/warp_first_call.py [--cases tri3:two quad4:two tri3:self quad4:self]
        [--backends DIR] [--run ID] [--out DIR]
    python benchmarks/warp_first_call.py --table MACHINE RUN [RUN ...]   # their records

Cases: element:two (`ac.detect` of the rough surfaces, 2000 nodes a surface) or element:self
(`ac.detect_self` of the crumpled sheet, 300 nodes): small scenes, so that compilation is
what the first call takes. float64 and the default device (the one-shot contract). Per
case: the first call, the second and the median of five more. --backends: the folder to
import the back ends from (default this checkout's; another commit's copy to compare). One
record per case to results/warp_first_call_<machine>.jsonl.
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).parent
sys.path[:0] = [str(HERE.parent), str(HERE)]
import _records  # noqa: E402


def child(element, kind, cache):
    import warp as wp

    wp.config.quiet = True
    wp.config.kernel_cache_dir = cache
    import arraycontact as ac
    from arraycontact import scenes

    if kind == "self":
        s = scenes.crumpled_sheet(300, element=element)
        call = lambda: ac.detect_self(s.master, backend="warp", d_max=s.params["d_max"])  # noqa: E731
        slaves = len(s.master.nodes)
    else:
        s = scenes.rough_surfaces(2000, element=element)
        call = lambda: ac.detect(s.slave, s.master, backend="warp")  # noqa: E731
        slaves = len(s.slave)
    rec = dict(element=element, kind=kind, slaves=slaves, faces=s.master.n_faces)
    times = []
    for _ in range(7):
        t = time.perf_counter()
        c = call()
        times.append(time.perf_counter() - t)
    dev = wp.get_device()
    name = dev.name if dev.is_cuda else "cpu"
    assert c.dtype == "float64", c.dtype
    rec.update(
        device=name, first_s=times[0], second_s=times[1], steady_s=statistics.median(times[2:])
    )
    print(json.dumps(rec), flush=True)


def table(machine, runs):
    """First and second call per case (rows) and run (columns), from the records."""
    recs = _records.load("warp_first_call", machine)
    cases = list(dict.fromkeys(f"{r['element']}:{r['kind']}" for r in recs if r["run"] in runs))
    print("| case | " + " | ".join(f"{run}: first / second call" for run in runs) + " |")
    print("|---" * (len(runs) + 1) + "|")
    for case in cases:
        cells = []
        for run in runs:
            r = [x for x in recs if x["run"] == run and f"{x['element']}:{x['kind']}" == case]
            cells.append(f"{r[-1]['first_s']:.1f} s / {r[-1]['second_s']:.3f} s" if r else "")
        print(f"| {case} | " + " | ".join(cells) + " |")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument(
        "--cases", nargs="+", default=["tri3:two", "quad4:two", "tri3:self", "quad4:self"]
    )
    ap.add_argument("--backends", default=str(HERE.parent / "backends"))
    ap.add_argument("--run", default=None)
    ap.add_argument("--out", default=None)
    ap.add_argument("--table", nargs="+", metavar="MACHINE RUN", help="a table of runs")
    ap.add_argument("--child", nargs=3, help=argparse.SUPPRESS)  # element, kind, cache folder
    a = ap.parse_args()
    if a.child:
        return child(*a.child)
    if a.table:
        return table(a.table[0], a.table[1:])
    meta = _records.meta(a.run)
    backends = str(Path(a.backends).resolve())
    env = dict(os.environ, CUDA_CACHE_DISABLE="1")
    env["PYTHONPATH"] = os.pathsep.join([backends, str(HERE.parent), env.get("PYTHONPATH", "")])
    for case in a.cases:
        element, _, kind = case.partition(":")
        if kind not in ("two", "self"):
            raise ValueError(f"a case is element:two or element:self, got {case!r}")
        cache = tempfile.mkdtemp(prefix="warp_cache_")
        cmd = [sys.executable, __file__, "--child", element, kind, cache]
        out = subprocess.run(cmd, capture_output=True, text=True, env=env)
        lines = [x for x in out.stdout.splitlines() if x.startswith("{")]
        if out.returncode or not lines:
            raise SystemExit(f"{case}: {out.stderr[-2000:]}")
        rec = dict(json.loads(lines[-1]), backends=os.path.relpath(backends, HERE.parent))
        print(
            f"{case:12s} first {rec['first_s']:6.1f} s  second {rec['second_s']:.3f} s  "
            f"steady {rec['steady_s'] * 1e3:.1f} ms  ({rec['device']})",
            flush=True,
        )
        _records.append("warp_first_call", rec, meta, out=a.out)


if __name__ == "__main__":
    main()
