"""Public API: lazy back ends, bad input, empty sets, overflow protocol, scenes."""

import subprocess
import sys

import numpy as np
import pytest
from conftest import assert_matches_reference
from test_detect import random_scene

import arraycontact as ac
from arraycontact import scenes


def test_import_loads_no_backend():
    code = (
        "import sys, arraycontact, arraycontact.scenes, arraycontact.reference; "
        "print(sorted(m for m in ('jax', 'warp') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_backend_packages_importable():
    import arraycontact_jax
    import arraycontact_warp

    assert callable(arraycontact_jax.run_one_shot) and arraycontact_warp.AVAILABLE is True


MASTER, SLAVE = random_scene(0, n=4)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(mode="fast"), "mode must be one of"),
        (dict(backend="torch"), "backend must be .auto. or one of"),
        (dict(d_max=0.0), "d_max must be a positive"),
        (dict(d_max=np.nan), "d_max must be a positive"),
        (dict(dtype=np.float16), "dtype must be float32 or float64"),
        (dict(displacement=np.zeros((3, 2))), "displacement must be"),
        (dict(displacement=np.full((3, 3), np.inf)), "displacement must be"),
    ],
)
def test_bad_options(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ac.detect(SLAVE, MASTER, **kwargs)


@pytest.mark.parametrize(
    "slave, match",
    [
        (np.zeros((4, 2)), r"slave must have shape \[n, 3\]"),
        (np.array([[0, 0, 0], [1, np.nan, 0]]), "slave row 1 is not finite"),
        (np.array([[0, 0, "a"]]), "real numeric"),
        (np.array([[0, 0, np.inf]]), "slave row 0 is not finite"),
    ],
)
@pytest.mark.parametrize("backend", ["numpy", "jax", "warp"])
def test_bad_slaves(backend, slave, match):
    with pytest.raises(ValueError, match=match):
        ac.detect(slave, MASTER, backend=backend)


def test_bad_master():
    with pytest.raises(ValueError, match="master must be an arraycontact.Surface"):
        ac.detect(SLAVE, MASTER.points)


@pytest.mark.parametrize("backend", ["numpy", "jax", "warp"])
def test_empty_sets(backend):
    c = ac.detect(np.zeros((0, 3)), MASTER, backend=backend)
    assert len(c) == 0 and c.pairs().shape == (0, 2)
    empty = ac.Surface(np.zeros((0, 3)), np.zeros((0, 3), int), "tri3")
    c = ac.detect(SLAVE, empty, backend=backend, d_max=1.0)
    assert len(c) == len(SLAVE) and not c.active.any()
    assert (c.status == ac.Status.OUT_OF_RANGE).all() and (c.face == -1).all()


@pytest.mark.parametrize("backend", ["numpy", "jax", "warp"])
@pytest.mark.parametrize("mode", ["exact", "node"])
@pytest.mark.parametrize("far", [False, True])
def test_rows_without_an_answer_are_empty(backend, mode, far):
    """Rows no face answers (in the master's box or, far, out of it) hold NaN and -1 in the
    answer's fields, whether the back end or the assembly of the record blanks them."""
    sc = scenes.rough_surfaces(2**8, seed=3)
    x = sc.slave.copy()
    if far:
        x[::7] += 50.0  # out of the box: never searched
    c = ac.detect(x, sc.master, backend=backend, mode=mode)
    none = ~c.active & (c.status != ac.Status.PASSING_BY)
    assert none.sum() >= (len(x) // 7 if far else 1)
    for k in ("xi", "point", "gap", "distance", "normal"):
        assert np.isnan(getattr(c, k)[none]).all(), k
    assert (c.face[none] == -1).all() and (c.feature[none] == int(ac.Feature.NONE)).all()
    # and the answered rows keep theirs
    assert c.active.sum() > len(x) // 2 and not np.isnan(c.gap[c.active]).any()
    assert (c.face[c.active] >= 0).all()


def test_jax_overflow_is_reported_and_replanned(monkeypatch):
    import arraycontact_jax._detect as jd
    import jax

    # Plan with room for one candidate face a slave: the one-shot call must grow and re-run.
    # (The count is a jitted program: the plan compiles it apart, see jd.once.)
    count = jax.jit(lambda *a, st: {"face_candidates": 1}, static_argnames=("st",))
    monkeypatch.setattr(jd, "_count", count)
    monkeypatch.setattr(jd, "MIN_CANDIDATES", 1)
    c = ac.detect(SLAVE, MASTER, backend="jax")
    ref = ac.detect(SLAVE, MASTER, backend="numpy")
    assert not c.overflow
    assert all(c.counts.count[k] <= v for k, v in c.counts.capacity.items())
    assert c.counts.capacity["face_candidates"] > 1  # grown after the first run overflowed
    assert np.array_equal(c.face, ref.face) and np.allclose(c.gap[c.active], ref.gap[c.active])


def test_jax_kernel_flags_overflow():
    """The low-level kernel reports counts above capacity instead of hiding them."""
    import arraycontact_jax._detect as jd
    import jax

    from arraycontact._detect import Static, master_arrays, scalars
    from arraycontact._prepare import prepare

    with jax.enable_x64(True):
        prep = prepare(SLAVE, MASTER, MASTER.longest_edge)
        st = Static("tri3", "exact", prep.node_levels, prep.face_levels, 0, False)
        m = master_arrays(MASTER, prep, np.float64)
        sc = scalars(prep, MASTER, np.float64)
        _, counts = jd._kernel(
            sc, m, SLAVE[prep.slave_rows], st=st, capacity=(("face_candidates", 2),)
        )
    # The true count (the most candidate faces of one slave) next to the capacity it exceeds.
    assert int(counts["face_candidates"]) > 2


def test_contacts_summary_and_status():
    c = ac.detect(SLAVE, MASTER, backend="numpy")
    text = c.summary()
    assert f"active: {c.active.sum()}" in text
    assert set(np.unique(c.status)) <= {int(s) for s in ac.Status}
    assert (c.feature[~c.active] == ac.Feature.NONE).all()


@pytest.mark.parametrize(
    "make",
    [
        lambda: scenes.rough_surfaces(2**8),
        lambda: scenes.rough_surfaces(2**9, element="quad9"),
        lambda: scenes.rough_layers(2**8, quadratic=True),
        lambda: scenes.sphere_on_plane(2**8),
        lambda: scenes.cylinder_on_road(2**8),
        lambda: scenes.curved_patch(4, element="tri6"),
    ],
)
def test_scenes_are_deterministic(make):
    a, b = make(), make()
    assert np.array_equal(a.slave, b.slave) and np.array_equal(a.master.points, b.master.points)
    assert a.master.n_faces > 0 and len(a.slave) > 0
    # Masters face +z (their normals point at the slaves above them).
    assert (a.master.face_normals[:, 2] > 0).all()


def test_rough_surface_sizes_and_roughness():
    s = scenes.rough_surfaces(2**12, rms=0.5, gap=3.0)
    assert len(s.slave) == 2**12 and len(s.master.nodes) == 2**12
    assert np.std(s.master.points[:, 2]) == pytest.approx(0.5)
    assert np.mean(s.slave[:, 2]) == pytest.approx(3.0, abs=1e-9)
    assert (s.slave_surface.face_normals[:, 2] < 0).all()


def test_graded_scenes_reject_bad_parameters():
    with pytest.raises(ValueError, match="ratio"):
        scenes.graded_surfaces(2**8, ratio=0.5)
    with pytest.raises(ValueError, match="n_fine"):
        scenes.fine_patch(1)
    with pytest.raises(ValueError, match="growth"):
        scenes.fine_patch(8, growth=1.0)
    with pytest.raises(ValueError, match="ratio"):
        scenes.fine_patch(8, ratio=float("nan"))


def test_default_contract_is_float64_on_every_backend():
    """`ac.detect(slave, master)` computes in float64 whichever back end answers, and the
    answer says which one did; "auto" picks Warp (on its default device: the CPU here, a GPU
    where one is visible) since it imports."""
    import jax
    import warp as wp

    devices = {"numpy": "cpu", "warp": str(wp.get_device()), "jax": jax.devices()[0].platform}
    for backend in ("auto", "numpy", "jax", "warp"):
        c = ac.detect(SLAVE, MASTER, backend=backend)
        assert c.dtype == "float64" and c.gap.dtype == np.float64
        assert c.backend == ("warp" if backend == "auto" else backend)
        assert c.device.startswith(devices[c.backend])
        assert f"backend: {c.backend} on {c.device}, float64" in c.summary()
        # float64 agreement, not float32's (the Warp back end once defaulted to float32)
        assert_matches_reference(c, SLAVE, MASTER, dtype=np.float64)
    c32 = ac.detect(SLAVE, MASTER, dtype="float32")
    assert c32.dtype == "float32"
