"""The Warp face-scan kernel's register cap against its time (GPU only): the same kernel
compiled with cuda_max_registers = each value given (0: no cap) and launched through
`arraycontact_warp.detect` on the rough_close scene; CUDA activity timing of the kernel,
median of the repeats, outputs checked equal to the shipped kernel's.

    python benchmarks/gpu_registers.py --log2 20 --caps 0 56 64 72 96 128
    python benchmarks/gpu_registers.py --log2 17 --self spiral_strip --caps 0 128 168

--self: self-contact's face-scan kernel on that scene (arraycontact.scenes, quad4).
"""

import argparse
import statistics
import sys
from pathlib import Path

import numpy as np

from arraycontact._backends import quiet_warp

sys.path.insert(0, str(Path(__file__).parent))
from gpu import kernel_resources, warp_plan  # noqa: E402
from run import make_scene  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--log2", type=int, default=20)
    ap.add_argument("--caps", type=int, nargs="*", default=[0, 56, 64, 72, 96, 128])
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--self", help="a self-contact scene")
    a = ap.parse_args()
    import arraycontact_warp as acw
    import warp as wp
    from arraycontact_warp import _detect

    quiet_warp()
    wp.init()
    name = "_self_face_kernel" if a.self else "_face_kernel"
    if a.self:
        import arraycontact as ac

        sc = getattr(ac.scenes, a.self)(2**a.log2, element="quad4")
        p = acw.plan_self(sc.master, d_max=sc.params["d_max"], device="cuda")
        x = wp.array((sc.master.points - p.origin).astype(np.float32), dtype=wp.vec3)
        p.origin = np.zeros(3)

        def detect():
            acw.detect_self(p, x)
    else:
        p, xs, xm = warp_plan(make_scene("rough_close", a.log2))

        def detect():
            acw.detect(p, xs, xm)

    p.graphs = False  # launches one by one: each call runs the kernels it names
    detect()
    shipped = {k: v.numpy().copy() for k, v in p.out.items()}
    base = getattr(_detect, name)
    # The shipped module's options; a module of its own per variant.
    options = {"enable_backward": False, "max_unroll": 1}
    try:
        for cap in a.caps:
            extra = {"cuda_max_registers": cap} if cap else {}
            variant = wp.kernel(module="unique", module_options=options, **extra)(base.func)
            setattr(_detect, name, variant)
            detect()
            times = []
            for _ in range(a.repeats):
                with wp.ScopedTimer(
                    "k", cuda_filter=wp.TIMING_KERNEL, synchronize=True, print=False
                ) as t:
                    detect()
                times.append(sum(r.elapsed for r in t.timing_results if "_face_kernel" in r.name))
            same = all(
                np.array_equal(v.numpy(), shipped[k], equal_nan=True) for k, v in p.out.items()
            )
            print(
                f"cap {cap or 'none'}: kernel {statistics.median(times):.3f} ms, "
                f"same outputs {same}",
                flush=True,
            )
    finally:
        setattr(_detect, name, base)
    for name, v in kernel_resources("cuda").items():
        if "_face_kernel" in name:
            print(f"{name}: {v['registers']} registers, {v['local_bytes']} local bytes")


if __name__ == "__main__":
    main()
