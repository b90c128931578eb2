"""The sharded JAX plan's set-up time on the devices this machine has (a mesh of all of
them, or --devices): a first plan (it compiles) and a second of the same scene with the
slaves moved by 1e-4 (compiled programs), per scene; --profile DIR writes each plan's
cProfile (cumulative and own times; the main thread's: the parts' host work runs in threads).

    python benchmarks/sharded_plan.py --log2 20 --scenes rough graded
"""

import argparse
import contextlib
import cProfile
import pstats
import time
from pathlib import Path

import arraycontact_jax as acj
import jax
import numpy as np
from jax.sharding import Mesh
from sharding import _scene


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--log2", type=int, default=16)
    ap.add_argument("--scenes", nargs="*", default=["rough", "graded"])
    ap.add_argument("--search", default="jax", choices=["jax", "warp"])
    ap.add_argument("--devices", type=int, default=len(jax.devices()))
    ap.add_argument("--profile", type=Path, default=None)
    a = ap.parse_args()
    mesh = Mesh(np.array(jax.devices()[: a.devices]), ("space",))
    for name in a.scenes:
        s = _scene(name, 1 << a.log2)
        for k in range(2):
            prof = cProfile.Profile() if a.profile else None
            t = time.perf_counter()
            with prof or contextlib.nullcontext():
                acj.plan(s.master, s.slave + 1e-4 * k, dtype="float32", mesh=mesh, search=a.search)
            dt = time.perf_counter() - t
            what = f"{name} 2^{a.log2} {a.search} {a.devices} device(s) plan {k + 1}"
            print(f"{what}: {dt:.2f} s")
            if prof:
                a.profile.mkdir(parents=True, exist_ok=True)
                out = a.profile / f"{name}_{a.log2}_{a.search}_{a.devices}_plan{k + 1}.txt"
                with open(out, "w") as f:
                    for key in ("cumulative", "tottime"):
                        pstats.Stats(prof, stream=f).sort_stats(key).print_stats(50)


if __name__ == "__main__":
    main()
