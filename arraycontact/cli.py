"""Command line: `arraycontact demo` and `arraycontact detect MASTER SLAVE -o OUT.vtu`."""

from __future__ import annotations

import argparse
import sys
import threading
import time
from contextlib import contextmanager

import numpy as np


class Progress:
    """Stages on stderr, for runs long enough to wait for: once the run has taken `after`
    seconds, a live line "stage... 3.5 s" while a stage runs, and "stage: 3.52 s" when it
    ends (quiet on small scenes, whose report comes at once)."""

    def __init__(self, after=1.0, stream=None):
        self.t0 = time.perf_counter()
        self.after = after
        self.stream = stream or sys.stderr

    def _late(self):
        return time.perf_counter() - self.t0 > self.after

    @contextmanager
    def stage(self, label):
        start = time.perf_counter()
        done = threading.Event()

        def tick():
            while not done.wait(0.25):
                if self._late():
                    t = time.perf_counter() - start
                    print(f"\r{label}... {t:5.1f} s", end="", file=self.stream, flush=True)

        t = threading.Thread(target=tick, daemon=True)
        t.start()
        ok = False
        try:
            yield
            ok = True
        finally:
            done.set()
            t.join()
            if self._late():
                t = time.perf_counter() - start
                if ok:
                    print(f"\r{label}: {t:.2f} s   ", file=self.stream, flush=True)
                else:  # a failed stage: its live line is erased, the error is the one line
                    blank = " " * (len(label) + 12)
                    print(f"\r{blank}\r", end="", file=self.stream, flush=True)


def topology(surface, backend):
    """Derive what a detection on `backend` reads from a Surface (a stage of its own in the
    progress): the Warp back end's topology on its device, else the Surface's NumPy tables."""
    from ._backends import load, resolve

    if resolve(backend) == "warp":
        load("warp").master_scalars(surface)
        return
    for name in ("nodes", "node_faces", "edges", "face_bounds", "node_normals", "longest_edge"):
        getattr(surface, name)


def write_vtu(path, contacts, slave_x):
    """Slave nodes (vertex cells) and contact elements as lines from each active slave to its
    closest point, with gap, distance, normal, face, feature and status as point data."""
    import meshio

    a = np.asarray(contacts.active)
    n = len(slave_x)
    pts = np.r_[slave_x, contacts.point[a]]
    k = np.arange(n)
    lines = np.stack([k[a], n + np.arange(a.sum())], -1)

    def both(v):
        v = np.asarray(v)
        return np.r_[v, v[a]]

    data = {
        name: both(getattr(contacts, name)).astype(float)
        for name in ("gap", "distance", "face", "feature", "status", "master_node")
    }
    data["active"] = both(a).astype(np.int8)
    data["normal"] = both(contacts.normal)
    data["slave_id"] = both(contacts.slave_ids).astype(float)
    cells = [("vertex", k[:, None])] + ([("line", lines)] if len(lines) else [])
    meshio.write(path, meshio.Mesh(pts, cells, point_data=data))


def write_png(path, contacts, slave_x, title):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    a = np.asarray(contacts.active)
    fig, ax = plt.subplots(figsize=(7, 6))
    ax.scatter(slave_x[~a, 0], slave_x[~a, 1], s=1, c="0.85", lw=0)
    sc = ax.scatter(
        slave_x[a, 0],
        slave_x[a, 1],
        s=2,
        c=contacts.gap[a],
        cmap="coolwarm_r",
        lw=0,
        vmin=-np.abs(contacts.gap[a]).max() if a.any() else -1,
        vmax=np.abs(contacts.gap[a]).max() if a.any() else 1,
    )
    fig.colorbar(sc, label="signed gap (negative: penetration)")
    ax.set_aspect("equal")
    ax.set_title(title)
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _report(c, label):
    print(label)
    print(c.summary())
    print(f"contact elements (slave, face), first 3: {c.pairs()[:3].tolist()}")
    print("time per stage: " + ", ".join(f"{k} {v * 1e3:.1f} ms" for k, v in c.timings.items()))


def demo(args):
    import arraycontact as ac

    progress = Progress()
    with progress.stage("making the scene"):
        scene = ac.scenes.rough_surfaces(args.nodes, gap=args.gap, element=args.element)
    with progress.stage("master topology"):
        topology(scene.master, args.backend)
    label = (
        f"rough surfaces (seed 000 Fig. 10): {len(scene.slave)} slave nodes, "
        f"{scene.master.n_faces} {args.element} master faces, mode {args.mode}"
    )
    with progress.stage("detecting"):
        c = ac.detect(
            scene.slave_surface,
            scene.master,
            backend=args.backend,
            mode=args.mode,
            dtype=args.dtype,
        )
    _report(c, label)
    write_vtu(f"{args.output}.vtu", c, scene.slave)
    write_png(f"{args.output}.png", c, scene.slave, "gap field on the slave surface")
    print(f"wrote {args.output}.vtu and {args.output}.png")
    return 0


def detect_files(args):
    import arraycontact as ac

    progress = Progress()
    with progress.stage(f"reading {args.master}"):
        master = ac.read_surface(args.master, file_format=args.format)
    with progress.stage(f"reading {args.slave}"):
        slave = ac.read_surface(args.slave, file_format=args.format)
    with progress.stage("master topology"):
        topology(master, args.backend)
    with progress.stage("detecting"):
        c = ac.detect(
            slave, master, backend=args.backend, mode=args.mode, d_max=args.d_max, dtype=args.dtype
        )
    _report(c, f"{args.slave} on {args.master}")
    write_vtu(args.output, c, slave.points[slave.nodes])
    print(f"wrote {args.output}")
    return 0


def jax_cache():
    """JAX compiles its programs again in every process. The command line, an application
    (the library leaves JAX's settings alone), keeps them in JAX's persistent compilation
    cache, so that a later run on meshes of the same sizes loads them: at 2^20 nodes on an
    H100 the first JAX detection of a process takes 8.3-9.1 s cold and 1.4-2.1 s warm
    (benchmarks/jax_first_call.py). The folder: $ARRAYCONTACT_JAX_CACHE (empty: no cache),
    default ~/.cache/arraycontact/jax; JAX's own setting, where made, wins."""
    import os

    import jax

    if jax.config.jax_compilation_cache_dir:
        return
    default = os.path.join(os.path.expanduser("~"), ".cache", "arraycontact", "jax")
    folder = os.environ.get("ARRAYCONTACT_JAX_CACHE", default)
    if folder:
        jax.config.update("jax_compilation_cache_dir", folder)
        # Every program: a run's small ones add up too.
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)


def main(argv=None):
    p = argparse.ArgumentParser(prog="arraycontact", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)

    def common(q):
        q.add_argument(
            "--backend",
            default="auto",
            choices=["auto", "numpy", "jax", "warp"],
            help="auto: Warp (GPU, else CPU) when it imports, else NumPy",
        )
        q.add_argument("--mode", default="exact", choices=["exact", "node"])
        q.add_argument("--dtype", default="float64", choices=["float64", "float32"])

    d = sub.add_parser("demo", help="detect contact between two built-in rough surfaces")
    d.add_argument("--nodes", type=int, default=2**16, help="nodes per surface")
    d.add_argument("--gap", type=float, default=1.0, help="mean-plane gap (element sizes)")
    d.add_argument("--element", default="tri3", choices=["tri3", "quad4", "tri6", "quad8", "quad9"])
    d.add_argument("-o", "--output", default="arraycontact-demo", help="output file stem")
    common(d)
    d.set_defaults(func=demo)
    f = sub.add_parser("detect", help="detect contact between two mesh files (any meshio format)")
    f.add_argument("master")
    f.add_argument("slave")
    f.add_argument("-o", "--output", required=True, help="output .vtu")
    f.add_argument("--d-max", type=float, default=None)
    f.add_argument(
        "--format",
        default=None,
        help="meshio's name of the files' format, when the extension does not tell",
    )
    common(f)
    f.set_defaults(func=detect_files)
    args = p.parse_args(argv)
    from ._backends import resolve

    if resolve(args.backend) == "warp":
        from ._backends import quiet_warp

        quiet_warp()  # no banner or kernel-cache lines in the report
    elif resolve(args.backend) == "jax":
        jax_cache()
    try:
        return args.func(args)
    except (ValueError, OSError) as e:  # bad input or an output that cannot be written
        print(f"arraycontact: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
