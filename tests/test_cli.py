"""The command line: demo and file-to-file detection."""

import meshio
import numpy as np

import arraycontact as ac
from arraycontact.cli import main


def test_demo(tmp_path, capsys):
    stem = tmp_path / "demo"
    assert main(["demo", "--nodes", "1024", "-o", str(stem)]) == 0
    out = capsys.readouterr().out
    assert "active:" in out and "time per stage" in out and "min gap" in out
    import warp as wp

    # The default: auto (Warp, on its default device: the CPU here, a GPU where visible), float64.
    assert f"backend: warp on {wp.get_device()}, float64" in out
    mesh = meshio.read(f"{stem}.vtu")
    assert (stem.parent / "demo.png").stat().st_size > 1000
    n_active = int(out.split("active: ")[1].split()[0])
    assert len(mesh.cells_dict["line"]) == n_active
    assert mesh.point_data["gap"].shape == (1024 + n_active,)


def test_progress_lists_the_stages_of_a_long_run():
    import io
    import time

    from arraycontact.cli import Progress

    out = io.StringIO()
    p = Progress(after=0.0, stream=out)
    with p.stage("reading"):
        time.sleep(0.3)
    with p.stage("detecting"):
        pass
    lines = [line.split("\r")[-1].strip() for line in out.getvalue().split("\n") if line]
    assert lines[0].startswith("reading: 0.3") and lines[-1].startswith("detecting: 0.0")
    quiet = io.StringIO()
    with Progress(after=60.0, stream=quiet).stage("reading"):
        pass
    assert quiet.getvalue() == ""
    # A stage that fails leaves no line of its own: the error that follows is the one line.
    failed = io.StringIO()
    try:
        with Progress(after=0.0, stream=failed).stage("reading"):
            time.sleep(0.3)
            raise ValueError("unreadable")
    except ValueError:
        pass
    assert "reading" in failed.getvalue() and "\n" not in failed.getvalue()
    assert failed.getvalue().endswith("\r")


def test_detect_files(tmp_path, capsys):
    s = ac.scenes.rough_surfaces(2**8, gap=0.5)
    mpath, spath = tmp_path / "master.vtu", tmp_path / "slave.msh"
    meshio.write(mpath, meshio.Mesh(s.master.points, [("triangle", s.master.faces)]))
    meshio.write(
        spath,
        meshio.Mesh(s.slave_surface.points, [("triangle", s.slave_surface.faces)]),
        file_format="gmsh22",
        binary=False,
    )
    out = tmp_path / "contacts.vtu"
    assert main(["detect", str(mpath), str(spath), "-o", str(out), "--mode", "node"]) == 0
    mesh = meshio.read(out)
    c = ac.detect(s.slave_surface, s.master, mode="node", backend="numpy")
    assert len(mesh.cells_dict["line"]) == c.active.sum()
    assert np.allclose(mesh.point_data["gap"][:256][c.active], c.gap[c.active])


def test_bad_input_is_a_clear_error(tmp_path, capsys):
    s = ac.scenes.rough_surfaces(2**8)
    path = tmp_path / "m.vtu"
    meshio.write(path, meshio.Mesh(s.master.points, [("triangle", s.master.faces)]))
    assert (
        main(["detect", str(path), str(path), "-o", str(tmp_path / "o.vtu"), "--d-max", "-1"]) == 2
    )
    assert "d_max must be a positive" in capsys.readouterr().err


def test_file_errors_are_one_line_and_status_2(tmp_path, capsys):
    s = ac.scenes.rough_surfaces(2**6)
    good = tmp_path / "m.vtu"
    meshio.write(good, meshio.Mesh(s.master.points, [("triangle", s.master.faces)]))
    garbage = tmp_path / "g.vtu"
    garbage.write_text("not a mesh")
    unknown = tmp_path / "m.xyz123"
    unknown.write_text("1 2 3")
    lines = meshio.Mesh(s.master.points, [("line", s.master.faces[:, :2])])
    no_faces = tmp_path / "lines.vtu"
    meshio.write(no_faces, lines)
    out = str(tmp_path / "o.vtu")
    cases = [
        (tmp_path / "missing.vtu", "no such file"),
        (garbage, "cannot read"),
        (unknown, "unknown mesh format"),
        (no_faces, str(no_faces)),
    ]
    for path, words in cases:
        assert main(["detect", str(good), str(path), "-o", out]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and str(path) in err and words in err, err
    # An output that cannot be written is one line too.
    assert main(["detect", str(good), str(good), "-o", str(tmp_path / "no" / "o.vtu")]) == 2
    assert capsys.readouterr().err.startswith("arraycontact: error:")


def test_jax_runs_keep_their_programs_in_a_persistent_cache(tmp_path):
    """`--backend jax` keeps its compiled programs in JAX's persistent cache, by default in
    ~/.cache/arraycontact/jax, so that a later run loads them; $ARRAYCONTACT_JAX_CACHE names
    another folder, and an empty value turns the cache off. In child processes (JAX's
    settings are the process's), each with a home of its own."""
    import os
    import subprocess
    import sys

    import warp as wp

    def demo(home, **own):
        home.mkdir()
        env = dict(os.environ, HOME=str(home), JAX_PLATFORMS="cpu")
        wp.init()  # (sets the kernel cache's folder, which the children share: no compiling)
        env["WARP_CACHE_PATH"] = wp.config.kernel_cache_dir
        for k in ("JAX_COMPILATION_CACHE_DIR", "ARRAYCONTACT_JAX_CACHE"):
            env.pop(k, None)
        env.update(own)
        cmd = ["demo", "--backend", "jax", "--nodes", "256", "-o", str(home / "demo")]
        run = subprocess.run(
            [sys.executable, "-m", "arraycontact.cli", *cmd],
            env=env,
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert run.returncode == 0, run.stderr[-2000:]
        assert "backend: jax" in run.stdout
        return home / ".cache" / "arraycontact" / "jax"

    default = demo(tmp_path / "a")
    assert len(list(default.iterdir())) > 0  # the programs, a file each
    assert not demo(tmp_path / "b", ARRAYCONTACT_JAX_CACHE="").exists()
    named = tmp_path / "named"
    assert not demo(tmp_path / "c", ARRAYCONTACT_JAX_CACHE=str(named)).exists()
    assert len(list(named.iterdir())) > 0
