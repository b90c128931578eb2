"""Every table of RESULTS.md and GPU.md, made from the records in results/*.jsonl.

    python benchmarks/report.py           # rewrite the tables from the records there
    python benchmarks/report.py --run     # first run the CPU suites (about 40 min here)
    python benchmarks/report.py --table detect    # print one of this script's tables

Each block between `<!-- table: ARGS -->` and `<!-- /table -->` in RESULTS.md, GPU.md and the
README is
replaced by the output of `python benchmarks/ARGS` (each benchmark prints its own tables from
its records); the block between `<!-- report -->` and `<!-- /report -->` of RESULTS.md holds
the CPU suites of run.py and skips.py, with results/pareto.png and results/scaling.png. Text
outside the blocks is left alone.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).parent
sys.path.insert(0, str(HERE))
import _records  # noqa: E402

RES = HERE / "results"
BEGIN, END = "<!-- report -->", "<!-- /report -->"
BLOCK = re.compile(r"(<!-- table: (.+?) -->\n)(.*?)(<!-- /table -->)", re.S)
DOCS = ("RESULTS.md", "GPU.md", "../README.md")


def load(name):
    """The CPU records of a suite, the newest one per configuration."""
    keys = ("scene", "log2_nodes", "backend", "dtype", "mode", "d_max_factor", "skip")
    return _records.newest(_records.load(name, "cpu"), *keys)


def _err(r):
    e = r["errors"]
    return e["miss_rate"] + e["wrong_face_rate"]


def pareto(records):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8))
    marks = {"numpy": "o", "jax": "s", "warp": "^"}
    for ax, scene in zip(axes, ("rough_close", "tyre_road")):
        rs = [r for r in records if r["scene"] == scene]
        for r in rs:
            face = "none" if r["dtype"] == "float32" else None
            colour = "C0" if r["mode"] == "exact" else "C3"
            ax.scatter(
                r["time_per_slave_s"] * 1e6,
                max(_err(r), 1e-4) * 100,
                marker=marks[r["backend"]],
                s=30 + 40 * r["d_max_factor"],
                facecolors=face,
                edgecolors=colour,
                color=colour,
            )
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("time per slave (us), steady state, this CPU")
        ax.set_ylabel("missed + wrong-face slaves (%)  [0 drawn at 0.01]")
        ax.set_title(f"{scene}, 2^{rs[0]['log2_nodes'] if rs else '?'} nodes per surface")
        ax.grid(True, which="both", alpha=0.3)
    axes[1].text(
        0.02,
        0.9,
        "blue: exact, red: node; o numpy, s jax, ^ warp;\n"
        "filled float64, hollow float32; size ~ d_max factor (0.5, 1, 2)",
        transform=axes[1].transAxes,
        fontsize=8,
    )
    fig.tight_layout()
    fig.savefig(RES / "pareto.png", dpi=110)
    lines = [
        "| scene | back end | dtype | mode | d_max x | time / slave | miss | wrong face | "
        "gap error / edge | active |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in sorted(
        records, key=lambda r: (r["scene"], r["mode"], r["backend"], r["dtype"], r["d_max_factor"])
    ):
        e = r["errors"]
        lines.append(
            f"| {r['scene']} | {r['backend']} | {r['dtype']} | {r['mode']} | "
            f"{r['d_max_factor']:g} | {r['time_per_slave_s'] * 1e6:.2f} us | "
            f"{e['miss_rate'] * 100:.2g} % | {e['wrong_face_rate'] * 100:.2g} % | "
            f"{e['max_gap_error_rel']:.1e} | {r['active']} |"
        )
    return lines


def scaling(records):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lines = [
        "| back end | nodes / surface | time / slave | peak bytes / node |",
        "|---|---|---|---|",
    ]
    fig, ax = plt.subplots(figsize=(6, 4.5))
    slopes = {}
    for backend in sorted({r["backend"] for r in records}):
        rs = sorted((r for r in records if r["backend"] == backend), key=lambda r: r["n_slaves"])
        n = np.array([r["n_slaves"] for r in rs], float)
        t = np.array([r["steady_s"] for r in rs])
        slopes[backend] = float(np.polyfit(np.log(n), np.log(t), 1)[0]) if len(rs) > 1 else None
        ax.loglog(n, t, "o-", label=f"{backend} {rs[0]['dtype']} (slope {slopes[backend]:.2f})")
        for r in rs:
            mem = f"{r['bytes_per_node']:.0f}" if "bytes_per_node" in r else "-"
            lines.append(
                f"| {backend} {r['dtype']} | 2^{r['log2_nodes']} | "
                f"{r['time_per_slave_s'] * 1e6:.2f} us | {mem} |"
            )
    ax.set_xlabel("slave nodes (= master nodes)")
    ax.set_ylabel("steady-state detection time (s), this CPU")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(RES / "scaling.png", dpi=110)
    lines.append("")
    lines.append(
        "Log-log slope of time against nodes (1 = linear): "
        + ", ".join(f"{b} {s:.2f}" for b, s in slopes.items() if s is not None)
        + "."
    )
    return lines


def peers(records):
    lines = [
        "| scene | arraycontact (exact) / peer | time | max distance error / edge |",
        "|---|---|---|---|",
    ]
    for r in records:
        e = r["errors"]
        lines.append(
            f"| {r['scene']} 2^{r['log2_nodes']} | arraycontact {r['backend']} "
            f"{r['dtype']} | {r['steady_s']:.3f} s | {e['max_gap_error_rel']:.1e} |"
        )
        if r["backend"] == "numpy":
            lines.append(
                f"| | scipy cKDTree (closest node only) | {r['peer']['steady_s']:.3f} s"
                f" | (no closest point) |"
            )
            for name, p in r.get("peers", {}).items():
                if "error" in p:
                    lines.append(f"| | {name} | {p['error']} | |")
                else:
                    lines.append(
                        f"| | {name} | {p['steady_s']:.3f} s | {p['max_distance_error_rel']:.1e} |"
                    )
    return lines


def table1(records):
    paper = {
        "table1_close": ("2,100,000", "75,300", "35 min"),
        "table1_convex": ("340,000", "15,800", "1 min"),
        "table1_apart": ("50,000", "0", "4 s"),
    }
    lines = [
        "| case | back end | nodes in box | active (within d_max) | penetrating | time | "
        "paper: nodes in box, contact elements, time |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in records:
        n_box = r.get("nodes_in_box", "-")
        lines.append(
            f"| {r['scene']} | {r['backend']} {r['dtype']} | {n_box:,} | "
            f"{r['active']:,} | {r.get('penetrating', '-'):,} | {r['steady_s']:.2f} s | "
            + ", ".join(paper[r["scene"]])
            + " |"
        )
    return lines


SUITES = ("pareto", "scaling", "peers", "table1")


def run_all():
    import subprocess
    import sys

    for suite in SUITES:
        subprocess.run([sys.executable, str(HERE / "run.py"), suite], check=True)
    subprocess.run([sys.executable, str(HERE / "skips.py")], check=True)


def skips(rec):
    return ["| skip | with | without | saved |", "|---|---|---|---|"] + [
        f"| {r['skip']} | {r['with_skip_s'] * 1e3:.1f} ms | {r['without_skip_s'] * 1e3:.1f} ms "
        f"| {r['saved_fraction'] * 100:.0f} % |"
        for r in rec
    ]


# (records, heading, introduction, table) of each RESULTS.md section, in order.
SECTIONS = [
    (
        "pareto",
        "Run time against error — `python benchmarks/run.py pareto`",
        "Every back end x dtype x mode x d_max factor (times the default d_max) on the rough "
        "surfaces and the tyre on a rough road, 2^14 nodes each; errors against the reference on "
        "256 random slaves. Plot: `results/pareto.png`.",
        pareto,
    ),
    (
        "scaling",
        "Scaling — `python benchmarks/run.py scaling`",
        "Rough surfaces, 2^12 .. 2^22 nodes each; peak bytes per node is the largest NumPy "
        "allocation of one call (tracemalloc) over slave + master nodes. Plot: "
        "`results/scaling.png`.",
        scaling,
    ),
    (
        "skips",
        "What each skip saves — `python benchmarks/skips.py`",
        "The same scene with and without each skip in one run on this CPU (NumPy float64; the "
        "static master on Warp's CPU device, the only back end that keeps a grid between calls); "
        "the scenes are in the script.",
        skips,
    ),
    (
        "table1",
        "Seed 000 Table 1 at 2^20 nodes per surface — `python benchmarks/run.py table1`",
        "quad4 faces, two rough surfaces of 2^20 nodes each: close (gap 1, RMS 0.5), convex "
        "(curvature 2e-4), close but apart (convex, gap 4). Nodes in box = slaves + master nodes "
        "inside the grown-box intersection. The paper's times are from its 2012 hardware and "
        "code; ours from Warp's CPU device on this 2-core machine (NumPy's quad4 Newton path "
        "takes minutes per call at this size here).",
        table1,
    ),
    (
        "peers",
        "Peers on the same points — `python benchmarks/run.py peers`",
        "Open3D, libigl and Warp's BVH answer the unsigned closest-point question (no feature, no "
        "signed gap, no tie rule); they are built and queried on the same points in the same run.",
        peers,
    ),
]


def detect_table():
    """The CPU detection of `run.py cpu`: every back end, dtype and mode against cKDTree."""
    recs = load("detect")
    rows = []
    for r in recs:
        e = r["errors"]
        rows.append(
            [
                f"2^{r['log2_nodes']}",
                r["backend"],
                r["dtype"],
                r["mode"],
                f"{r['first_call_s']:.2f} s",
                f"{r['steady_s']:.2f} s",
                f"{r['ratio_to_peer']:.1f}x",
                f"{e['miss_rate']:.2g}",
                f"{e['wrong_face_rate']:.1%}",
                f"{e['max_gap_error_rel']:.1e}",
                ", ".join(
                    f"{k} {v * 1e3:.0f}"
                    for k, v in r["stages_s"].items()
                    if k not in ("detect", "total")
                ),
            ]
        )
    header = [
        "nodes / surface", "back end", "dtype", "mode", "first call", "steady", "/ cKDTree",
        "miss", "wrong face", "gap error", "stages (ms)",
    ]  # fmt: skip
    peers = {r["log2_nodes"]: r["peer"]["steady_s"] for r in recs}
    print(_records.markdown(header, rows))
    print(
        "\ncKDTree (build + closest-node query), same runs: "
        + ", ".join(f"{v:.3f} s (2^{k})" for k, v in sorted(peers.items()))
        + f". Run {recs[0]['run']} ({recs[0]['device']}, {_records.commit(recs[0])})."
    )


TABLES = {"detect": detect_table}


def blocks(text):
    """Every `<!-- table: ARGS -->` block of `text` filled with `python benchmarks/ARGS`."""

    def fill(m):
        args = m.group(2).split()
        out = subprocess.run(
            [sys.executable, str(HERE / args[0]), *args[1:]],
            capture_output=True,
            text=True,
            check=True,
            cwd=HERE.parent,
        ).stdout.strip()
        return m.group(1) + out + "\n" + m.group(4)

    return BLOCK.sub(fill, text)


def main():
    if "--table" in sys.argv[1:]:
        return TABLES[sys.argv[sys.argv.index("--table") + 1]]()
    if "--run" in sys.argv[1:]:
        run_all()
    out = []
    for suite, heading, intro, render in SECTIONS:
        rec = load(suite)
        if rec:
            out += [f"### {heading}", "", intro, ""] + render(rec) + [""]
    for name in DOCS:
        f = HERE / name
        text = f.read_text()
        if name == "RESULTS.md":
            block = BEGIN + "\n" + "\n".join(out) + "\n" + END
            text = text[: text.index(BEGIN)] + block + text[text.index(END) + len(END) :]
        f.write_text(blocks(text))


if __name__ == "__main__":
    main()
