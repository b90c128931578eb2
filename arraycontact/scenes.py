"""Deterministic contact scenes for tests, the demo and the benchmarks.

Each generator returns a `Scene`: a master `Surface`, the slave node coordinates and (where the
slaves come from a surface mesh) that slave `Surface`. Lengths are in units of the master's
element size (grid spacing 1), so scenes of every size have the same local geometry.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ._surface import Surface

__all__ = [
    "Scene",
    "grid_surface",
    "rough_field",
    "rough_surfaces",
    "rough_layers",
    "sphere_on_plane",
    "cylinder_on_road",
    "curved_patch",
    "graded_surfaces",
    "fine_patch",
    "steep_rough_surfaces",
    "block_surface",
    "spiral_strip",
    "folded_sheet",
    "coil_spring",
    "crumpled_sheet",
    "two_bodies",
    "Step",
    "closing_step",
    "closing_rough_surfaces",
    "rolling_tyre",
]


@dataclass(frozen=True, eq=False)
class Scene:
    name: str
    master: Surface
    slave: np.ndarray
    slave_surface: Surface | None = None
    params: dict = field(default_factory=dict)


def _grid_shape(n_nodes):
    """(nx, ny) with nx * ny = n_nodes for powers of two, nearly square otherwise."""
    k = int(round(np.log2(max(n_nodes, 4))))
    if 2**k == n_nodes:
        return 2 ** ((k + 1) // 2), 2 ** (k // 2)
    s = max(int(round(np.sqrt(n_nodes))), 2)
    return s, s


def grid_surface(x, y, z, element="tri3", *, flip=False) -> Surface:
    """Surface on a structured grid of nodes x, y, z [nx, ny], outward normal +z (-z if flip).

    Quadratic elements take the grid as corner and mid-side nodes: nx and ny must be odd."""
    nx, ny = x.shape
    ids = np.arange(nx * ny).reshape(nx, ny)
    pts = np.stack([x, y, z], -1).reshape(-1, 3)
    if element in ("tri3", "quad4"):
        a, b, c, d = ids[:-1, :-1], ids[1:, :-1], ids[1:, 1:], ids[:-1, 1:]
        if element == "quad4":
            f = np.stack([a, b, c, d], -1).reshape(-1, 4)
        else:
            f = np.concatenate(
                [np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)]
            )
    else:
        if nx % 2 == 0 or ny % 2 == 0:
            raise ValueError("quadratic grid surfaces need an odd number of nodes per side")
        n = {
            (di, dj): ids[di : nx - 2 + di : 2, dj : ny - 2 + dj : 2]
            for di in range(3)
            for dj in range(3)
        }
        c0, c1, c2, c3 = n[0, 0], n[2, 0], n[2, 2], n[0, 2]
        m01, m12, m23, m30, mc = n[1, 0], n[2, 1], n[1, 2], n[0, 1], n[1, 1]
        if element == "tri6":
            f = np.concatenate(
                [
                    np.stack([c0, c1, c2, m01, m12, mc], -1).reshape(-1, 6),
                    np.stack([c0, c2, c3, mc, m23, m30], -1).reshape(-1, 6),
                ]
            )
        elif element == "quad8":
            f = np.stack([c0, c1, c2, c3, m01, m12, m23, m30], -1).reshape(-1, 8)
        elif element == "quad9":
            f = np.stack([c0, c1, c2, c3, m01, m12, m23, m30, mc], -1).reshape(-1, 9)
        else:
            raise ValueError(f"unknown element {element!r}")
    if flip:
        k = 3 if element.startswith("tri") else 4
        corners = np.concatenate([f[:, :1], f[:, 1:k][:, ::-1]], 1)
        if f.shape[1] > k:
            # Reversing the corner cycle c0 c1 .. c(k-1) reverses the edge order as well:
            # edge i of the flipped face is edge k-1-i of the original.
            mids = f[:, k : 2 * k][:, ::-1]
            f = np.concatenate([corners, mids, f[:, 2 * k :]], 1)
        else:
            f = corners
    return Surface(pts, f, element)


def rough_field(nx, ny, *, hurst=0.8, rms=1.0, seed=0, cutoff=None):
    """Self-affine random field on an nx x ny periodic grid (spectral synthesis, seed 000 Fig. 10).

    Power spectrum ~ |q|^-2(1+H) between the longest wavelength (the grid) and `cutoff`
    (default: 4 grid spacings, so that each element is nearly flat), scaled to the given RMS."""
    rng = np.random.default_rng(seed)
    qx = np.fft.fftfreq(nx)[:, None]
    qy = np.fft.rfftfreq(ny)[None, :]
    q = np.sqrt(qx**2 + qy**2)
    qmax = 1.0 / (cutoff or 4.0)
    amp = np.where((q > 0) & (q <= qmax), np.power(np.maximum(q, 1e-12), -(1 + hurst)), 0.0)
    phase = rng.uniform(0, 2 * np.pi, amp.shape)
    h = np.fft.irfft2(amp * np.exp(1j * phase), s=(nx, ny))
    std = h.std()
    return h * (rms / std) if std > 0 else h


def rough_surfaces(
    n_nodes=2**12, *, gap=1.0, rms=0.5, hurst=0.8, curvature=0.0, element="tri3", seed=0
) -> Scene:
    """Two rough surfaces facing each other (seed 000 Fig. 10).

    The master (normal +z) lies around z = 0, the slave surface (normal -z) around z = gap;
    both have `n_nodes` nodes and RMS roughness `rms` (in element sizes). `curvature` > 0 makes
    both convex (a paraboloid of that curvature), the Table 1 'two convex surfaces' case."""
    nx, ny = _grid_shape(n_nodes)
    if element in ("tri6", "quad8", "quad9"):
        nx, ny = nx - 1 + nx % 2, ny - 1 + ny % 2
    x, y = np.meshgrid(np.arange(nx, dtype=float), np.arange(ny, dtype=float), indexing="ij")
    x -= x.mean()
    y -= y.mean()
    bowl = 0.5 * curvature * (x**2 + y**2)
    z1 = rough_field(nx, ny, hurst=hurst, rms=rms, seed=seed) - bowl
    z2 = gap + rough_field(nx, ny, hurst=hurst, rms=rms, seed=seed + 1) + bowl
    master = grid_surface(x, y, z1, element)
    slave_surface = grid_surface(x, y, z2, element, flip=True)
    slave = slave_surface.points[slave_surface.nodes]
    return Scene(
        "rough_surfaces",
        master,
        slave,
        slave_surface,
        dict(
            n_nodes=nx * ny,
            gap=gap,
            rms=rms,
            hurst=hurst,
            curvature=curvature,
            element=element,
            seed=seed,
        ),
    )


def _graded_axis(spacing):
    """Node coordinates (centred on 0) from the element spacings along one axis."""
    x = np.r_[0.0, np.cumsum(spacing)]
    return x - 0.5 * x[-1]


def graded_surfaces(
    n_nodes=2**12, *, ratio=100.0, gap=1.0, rms=0.5, element="tri3", seed=0
) -> Scene:
    """`rough_surfaces` on graded grids: element size 1 at the centre growing geometrically to
    `ratio` at the border along each axis (so faces of every size between, stretched up to
    `ratio`:1 where a fine row crosses a coarse column), with the same node count for every
    ratio (the grading family of the benchmarks). Roughness and gap scale with the local
    element size, so that every part of the scene looks like the uniform one (ratio 1)."""
    if not (np.isfinite(ratio) and ratio >= 1):
        raise ValueError(f"ratio must be a finite number >= 1, got {ratio}")
    nx, ny = _grid_shape(n_nodes)

    def spacing(n):
        u = np.abs(np.linspace(-1.0, 1.0, n - 1))
        return float(ratio) ** u

    hx, hy = spacing(nx), spacing(ny)
    x, y = np.meshgrid(_graded_axis(hx), _graded_axis(hy), indexing="ij")
    # The local element size at each node: the smaller of the adjacent spacings' means.
    lx = np.r_[hx[0], 0.5 * (hx[1:] + hx[:-1]), hx[-1]]
    ly = np.r_[hy[0], 0.5 * (hy[1:] + hy[:-1]), hy[-1]]
    h = np.minimum(lx[:, None], ly[None, :])
    z1 = h * rough_field(nx, ny, rms=rms, seed=seed)
    z2 = h * (gap + rough_field(nx, ny, rms=rms, seed=seed + 1))
    master = grid_surface(x, y, z1, element)
    slave_surface = grid_surface(x, y, z2, element, flip=True)
    return Scene(
        "graded_surfaces",
        master,
        slave_surface.points[slave_surface.nodes],
        slave_surface,
        dict(n_nodes=nx * ny, ratio=ratio, gap=gap, rms=rms, element=element, seed=seed),
    )


def fine_patch(
    n_fine=64, *, ratio=1000.0, growth=1.5, n_slaves=None, gap=0.5, rms=0.3, element="tri3", seed=0
) -> Scene:
    """A fine patch (n_fine x n_fine elements of size 1) inside a coarse plate (elements of size
    `ratio`), joined by rows growing by `growth` per element, and a rough slave punch of
    `n_slaves` nodes (default n_fine^2) over the patch at mean height `gap`: the contact zone
    meshed 1000x finer than the rest of the body, as finite-element users mesh it."""
    if not (isinstance(n_fine, (int, np.integer)) and n_fine >= 2):
        raise ValueError(f"n_fine must be an integer >= 2, got {n_fine}")
    if not (np.isfinite(ratio) and ratio >= 1):
        raise ValueError(f"ratio must be a finite number >= 1, got {ratio}")
    if not (np.isfinite(growth) and growth > 1):
        raise ValueError(f"growth must be a finite number > 1, got {growth}")
    n_grow = int(np.ceil(np.log(ratio) / np.log(growth)))
    grow = np.minimum(growth ** np.arange(1, n_grow + 1), ratio)
    side = np.r_[grow, np.full(max(n_fine // 4, 4), float(ratio))]
    spacing = np.r_[side[::-1], np.ones(n_fine), side]
    x, y = np.meshgrid(_graded_axis(spacing), _graded_axis(spacing), indexing="ij")
    master = grid_surface(x, y, np.zeros_like(x), element)
    n = n_slaves or n_fine * n_fine
    ns = int(np.sqrt(n))
    u = np.linspace(-0.45, 0.45, ns) * n_fine
    sx, sy = np.meshgrid(u, u, indexing="ij")
    sz = gap + rough_field(ns, ns, rms=rms, seed=seed)
    slave = np.stack([sx, sy, sz], -1).reshape(-1, 3)
    return Scene(
        "fine_patch",
        master,
        slave,
        None,
        dict(
            n_fine=n_fine,
            ratio=ratio,
            growth=growth,
            n_slaves=len(slave),
            gap=gap,
            rms=rms,
            element=element,
            seed=seed,
        ),
    )


def steep_rough_surfaces(n_nodes=2**12, *, rms=4.0, gap=4.0, seed=0) -> Scene:
    """`rough_surfaces` with a steep roughness (RMS 4 element sizes and a cutoff at 4 spacings:
    faces several times longer than their in-plane spacing), a uniform mesh whose faces are
    long needles for any structure sized by the longest edge."""
    s = rough_surfaces(n_nodes, gap=gap, rms=rms, seed=seed)
    return Scene(
        "steep_rough_surfaces",
        s.master,
        s.slave,
        s.slave_surface,
        dict(n_nodes=len(s.slave), rms=rms, gap=gap, seed=seed),
    )


def rough_layers(n_nodes=2**12, *, quadratic=False, rms=0.5, seed=0) -> Scene:
    """Two interpenetrating rough layers with the same mean plane (seed 003, section 5.2).

    Linear layers are tri3, quadratic ones tri6. About half the slave nodes are below the
    master surface, so gaps of both signs are present everywhere."""
    s = rough_surfaces(
        n_nodes, gap=0.0, rms=rms, element="tri6" if quadratic else "tri3", seed=seed
    )
    return Scene(
        "rough_layers",
        s.master,
        s.slave,
        s.slave_surface,
        dict(n_nodes=len(s.slave), quadratic=quadratic, rms=rms, seed=seed),
    )


def sphere_on_plane(n_nodes=2**12, *, radius=10.0, depth=0.5, element="quad4") -> Scene:
    """A sphere of `radius` pressed `depth` into a flat master plane.

    The master is a square grid of about `n_nodes` nodes and unit spacing, normal +z; the slaves
    are `n_nodes` nodes spread evenly over the sphere (a Fibonacci lattice)."""
    nx, ny = _grid_shape(n_nodes)
    if element in ("tri6", "quad8", "quad9"):
        nx, ny = nx - 1 + nx % 2, ny - 1 + ny % 2
    x, y = np.meshgrid(np.arange(nx, dtype=float), np.arange(ny, dtype=float), indexing="ij")
    master = grid_surface(x - x.mean(), y - y.mean(), np.zeros_like(x), element)
    k = np.arange(n_nodes) + 0.5
    phi = np.arccos(1 - 2 * k / n_nodes)
    theta = np.pi * (1 + 5**0.5) * k
    sphere = radius * np.stack(
        [np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], -1
    )
    slave = sphere + np.array([0.0, 0.0, radius - depth])
    return Scene(
        "sphere_on_plane",
        master,
        slave,
        None,
        dict(n_nodes=n_nodes, radius=radius, depth=depth, element=element),
    )


def cylinder_on_road(
    n_nodes=2**12, *, radius=20.0, width=None, depth=0.5, rms=0.3, element="tri3", seed=0
) -> Scene:
    """A cylinder (the tyre) pressed into a rough road (seed 000 section 2.3).

    The road is a rough master of about `n_nodes` nodes; the tyre's slave nodes (`n_nodes`
    of them) lie on a cylinder of axis y, sampled about as finely as the road."""
    road = rough_surfaces(n_nodes, gap=0.0, rms=rms, element=element, seed=seed).master
    xy = road.points[:, :2]
    width = width or float(np.ptp(xy[:, 1])) * 0.5
    n_around = max(int(np.sqrt(n_nodes * 2 * np.pi * radius / width)), 8)
    n_along = max(n_nodes // n_around, 2)
    a, yy = np.meshgrid(
        np.linspace(0, 2 * np.pi, n_around, endpoint=False),
        np.linspace(-width / 2, width / 2, n_along),
        indexing="ij",
    )
    top = road.points[:, 2].max()
    slave = np.stack(
        [radius * np.sin(a), yy, top + radius - depth - radius * np.cos(a)], -1
    ).reshape(-1, 3)
    return Scene(
        "cylinder_on_road",
        road,
        slave,
        None,
        dict(
            n_nodes=len(slave),
            radius=radius,
            width=width,
            depth=depth,
            rms=rms,
            element=element,
            seed=seed,
        ),
    )


def curved_patch(
    n_faces_side=8, *, element="quad9", curvature=0.3, gap=0.3, n_slaves=2000, seed=0
) -> Scene:
    """A doubly curved patch of quadratic (or linear) faces with slaves scattered around it.

    The master is z = curvature/2 (x^2 - 0.5 y^2) + 0.2 sin(x) cos(y) on n_faces_side^2 faces of
    unit size; slaves are uniform in the patch's footprint within +-gap (in element sizes) of
    the surface, so both signs of gap and points off every edge occur."""
    quadratic = element in ("tri6", "quad8", "quad9")
    m = 2 * n_faces_side + 1 if quadratic else n_faces_side + 1
    s = np.linspace(-n_faces_side / 2, n_faces_side / 2, m)
    x, y = np.meshgrid(s, s, indexing="ij")

    def height(x, y):
        return 0.5 * curvature * (x**2 - 0.5 * y**2) + 0.2 * np.sin(x) * np.cos(y)

    master = grid_surface(x, y, height(x, y), element)
    rng = np.random.default_rng(seed)
    u = rng.uniform(-n_faces_side / 2 - 0.5, n_faces_side / 2 + 0.5, (n_slaves, 2))
    z = height(u[:, 0], u[:, 1]) + rng.uniform(-gap, gap, n_slaves)
    slave = np.c_[u, z]
    return Scene(
        "curved_patch",
        master,
        slave,
        None,
        dict(
            n_faces_side=n_faces_side,
            element=element,
            curvature=curvature,
            gap=gap,
            n_slaves=n_slaves,
            seed=seed,
        ),
    )


#: Single elements in the plane z = 0 for the study of seed 003 section 5.1 (Fig. 4): a linear
#: triangle and quad, and quadratic ones whose mid nodes are moved off the straight edges (one
#: edge bulging out, one bent in), in the domains of the paper's lattices.
# Curved like seed 003 Fig. 4 (no coordinates are given there): quad8 with its right edge convex
# and the others concave, tri6 with its right and left edges convex.
STUDY_ELEMENTS = {
    "tri3": (np.array([[-0.6, -0.2], [0.6, -0.7], [0.5, 0.8]]), 2.0),
    "quad4": (np.array([[-0.8, -0.8], [0.9, -0.7], [0.8, 0.9], [-0.9, 0.7]]), 2.0),
    "tri6": (
        np.array([[-2.0, -1.8], [2.0, -1.5], [-1.2, 2.0], [0.0, -1.2], [0.8, 0.8], [-1.9, 0.1]]),
        6.0,
    ),
    "quad8": (
        np.array(
            [
                [-2.0, -2.0],
                [2.0, -1.8],
                [1.8, 2.0],
                [-2.0, 1.8],
                [0.0, -1.5],
                [2.3, 0.1],
                [0.0, 1.6],
                [-1.6, 0.0],
            ]
        ),
        6.0,
    ),
}


def single_element_study(element, n=100, lift=None):
    """Seed 003 section 5.1: one element and a n x n lattice of points on its plane.

    Returns (Surface, points [n*n, 3]). The lattice covers [-2, 2]^2 for linear elements and
    [-6, 6]^2 for quadratic ones. With `lift` (the 3-D case of Fig. 6, tri3 only) the right-most
    nodes move to z = lift and the lattice to the plane z = 2 over [-4, 4]^2."""
    xy, half = STUDY_ELEMENTS[element]
    pts = np.c_[xy, np.zeros(len(xy))]
    if lift is not None:
        right = xy[:, 0] > xy[:, 0].min() + 1e-9
        pts[right, 2] = lift
        half = 4.0
    s = np.linspace(-half, half, n)
    x, y = np.meshgrid(s, s, indexing="ij")
    z = np.full_like(x, 2.0 if lift is not None else 0.0)
    return Surface(pts, [np.arange(len(xy))], element), np.stack([x, y, z], -1).reshape(-1, 3)


# ---------------------------------------------------------------------------------------------
# Self-contact: thin bodies given as the closed surface of a mapped block (detect_self).


def block_surface(mapping, shape, element="quad4") -> Surface:
    """The closed surface of the block [0, 1]^3 sampled by a grid of `shape` = (nu, nv, nw)
    nodes and mapped by `mapping(u, v, w) -> (x, y, z)` (arrays of one shape), outward
    normals when the mapping preserves orientation. Quadratic elements need odd counts."""
    nu, nv, nw = shape
    u, v, w = np.meshgrid(*[np.linspace(0, 1, k) for k in shape], indexing="ij")
    x = np.stack(mapping(u, v, w), -1)
    ids = np.arange(x[..., 0].size).reshape(shape)
    points = x.reshape(-1, 3)
    faces = []
    for a in range(3):
        p, q = (a + 1) % 3, (a + 2) % 3  # e_p x e_q = e_a
        for end in (0, shape[a] - 1):
            side = np.moveaxis(ids, (a, p, q), (0, 1, 2))[end]
            xs = points[side]
            s = grid_surface(xs[..., 0], xs[..., 1], xs[..., 2], element, flip=end == 0)
            faces.append(side.reshape(-1)[s.faces])
    return Surface(points, np.concatenate(faces), element)


def _orient(mapping, shape):
    """`mapping` with w reversed where that makes its Jacobian positive (outward normals)."""
    u, v, w = (np.array([a]) for a in (0.37, 0.41, 0.5))
    eps = 1e-6
    x0 = np.stack(mapping(u, v, w), -1)[0]
    du, dv, dw = (
        (np.stack(mapping(u + eps * (k == 0), v + eps * (k == 1), w + eps * (k == 2)), -1)[0] - x0)
        for k in range(3)
    )
    if np.dot(np.cross(du, dv), dw) > 0:
        return mapping
    return lambda u, v, w: mapping(u, v, 1 - w)


def _counts(n_nodes, aspect, quadratic, nw=2):
    """(nu, nv, nw) with about n_nodes / 2 nodes a side and nu / nv = aspect."""
    nv = max(int(round(np.sqrt(n_nodes / (nw * aspect)))), 3)
    nu = max(int(round(n_nodes / (nw * nv))), 3)
    if quadratic:
        nu, nv, nw = nu + 1 - nu % 2, nv + 1 - nv % 2, max(nw + 1 - nw % 2, 3)
    return nu, nv, nw


def spiral_strip(
    n_nodes=2**12, *, turns=4.0, thickness=1.0, gap=0.3, height=None, element="quad4"
) -> Scene:
    """A thin strip wound into a flat spiral with `gap` between its turns (the snail
    operculum of seed 000 Fig. 12): a solid of `thickness`, its closed surface meshed with
    about `n_nodes` nodes, elements about as long as the thickness. Every turn faces the next
    across the gap; the back side of each turn lies `thickness` behind its front: detect with
    gap < d_max < thickness (params["d_max"])."""
    pitch = thickness + gap
    r0 = 4 * pitch
    quadratic = element in ("tri6", "quad8", "quad9")
    # Arc length of the mid-curve r = r0 + pitch theta / 2 pi over `turns`.
    theta_max = 2 * np.pi * turns
    length = r0 * theta_max + pitch * theta_max**2 / (4 * np.pi)
    if height is None:  # grows with the node count, as the length does not
        height = max(4.0, 0.5 * np.sqrt(n_nodes / 4))
    shape = _counts(n_nodes, length / height, quadratic)

    def mapping(u, v, w):
        th = theta_max * u
        r = r0 + pitch * th / (2 * np.pi) + (w - 0.5) * thickness
        return r * np.cos(th), r * np.sin(th), height * v

    surface = block_surface(_orient(mapping, shape), shape, element)
    return _self_scene("spiral_strip", surface, gap, thickness, element, turns=turns)


def folded_sheet(
    n_nodes=2**12, *, length=20.0, width=8.0, thickness=1.0, gap=0.3, element="quad4"
) -> Scene:
    """A plate of `thickness` folded back onto itself (a hairpin): two flat legs of `length`
    joined by a half circle, their facing sides `gap` apart."""
    quadratic = element in ("tri6", "quad8", "quad9")
    radius = 0.5 * (gap + thickness)  # mid-surfaces 2 radius apart: facing sides `gap`
    arc = np.pi * radius
    total = 2 * length + arc
    shape = _counts(n_nodes, total / width, quadratic)

    def mapping(u, v, w):
        s = u * total
        off = (w - 0.5) * thickness
        # Leg 1 along +x at z = -radius (normal -z outward), the arc, leg 2 back at z = +radius.
        t = np.clip((s - length) / radius, 0.0, np.pi)
        on1, on2 = s <= length, s >= length + arc
        cx = np.where(
            on1, s, np.where(on2, length - (s - length - arc), length + radius * np.sin(t))
        )
        cz = np.where(on1, -radius, np.where(on2, radius, -radius * np.cos(t)))
        nx = np.where(on1 | on2, 0.0, np.sin(t))
        nz = np.where(on1, -1.0, np.where(on2, 1.0, -np.cos(t)))
        return cx + off * nx, width * v, cz + off * nz

    surface = block_surface(_orient(mapping, shape), shape, element)
    return _self_scene("folded_sheet", surface, gap, thickness, element)


def coil_spring(
    n_nodes=2**12, *, turns=3.0, radius=6.0, side=1.0, gap=0.05, element="quad4"
) -> Scene:
    """A coil spring of square wire (`side`) whose turns nearly touch (`gap` apart)."""
    quadratic = element in ("tri6", "quad8", "quad9")
    pitch = side + gap
    length = turns * np.sqrt((2 * np.pi * radius) ** 2 + pitch**2)
    nu, nv, nw = _counts(4 * n_nodes, 0.5 * length / side, quadratic)
    # A quarter of those across the wire (radially): about n_nodes, elements longer along it.
    nv = nv // 4 * 2 + 1 if quadratic else max(nv // 4, 2)
    shape = (nu, nv, nw)

    def mapping(u, v, w):
        th = 2 * np.pi * turns * u
        r = radius + (v - 0.5) * side
        return r * np.cos(th), r * np.sin(th), pitch * th / (2 * np.pi) + (w - 0.5) * side

    surface = block_surface(_orient(mapping, shape), shape, element)
    return _self_scene("coil_spring", surface, gap, side, element, turns=turns)


def crumpled_sheet(
    n_nodes=2**12, *, thickness=0.5, amplitude=0.25, element="quad4", seed=0
) -> Scene:
    """A thin sheet crumpled by a steep random displacement field (`amplitude` times the
    sheet's side, the same shape at every size): its folds lean over each other, some closer
    than d_max, some through each other (negative gaps)."""
    quadratic = element in ("tri6", "quad8", "quad9")
    shape = _counts(n_nodes, 1.0, quadratic)
    nu, nv, _ = shape
    amplitude = amplitude * nu
    side = float(nu)
    hx = rough_field(nu, nv, rms=amplitude, seed=seed, cutoff=max(nu / 4, 4))
    hy = rough_field(nu, nv, rms=amplitude, seed=seed + 1, cutoff=max(nu / 4, 4))
    hz = rough_field(nu, nv, rms=amplitude, seed=seed + 2, cutoff=max(nu / 4, 4))

    def mapping(u, v, w):
        i = np.clip(np.rint(u * (nu - 1)).astype(int), 0, nu - 1)
        j = np.clip(np.rint(v * (nv - 1)).astype(int), 0, nv - 1)
        x, y = side * u + hx[i, j], side * v + hy[i, j]
        return x, y, hz[i, j] + (w - 0.5) * thickness

    surface = block_surface(mapping, shape, element)
    return _self_scene("crumpled_sheet", surface, None, thickness, element, seed=seed)


def two_bodies(n_nodes=2**12, *, gap=0.3, thickness=1.0, element="quad4") -> Scene:
    """Two thin plates in one surface, one above the other `gap` apart, the upper one turned
    by 10 degrees: contact between bodies of one surface (the multibody case)."""
    quadratic = element in ("tri6", "quad8", "quad9")
    shape = _counts(n_nodes // 2, 1.0, quadratic)
    side = float(shape[0])
    turn = np.deg2rad(10.0)

    def lower(u, v, w):
        return side * (u - 0.5), side * (v - 0.5), thickness * (w - 1)

    def upper(u, v, w):
        x, y = side * (u - 0.5), side * (v - 0.5)
        c, s = np.cos(turn), np.sin(turn)
        return c * x - s * y, s * x + c * y, gap + thickness * w

    a = block_surface(lower, shape, element)
    b = block_surface(upper, shape, element)
    surface = Surface(
        np.concatenate([a.points, b.points]),
        np.concatenate([a.faces, b.faces + len(a.points)]),
        element,
    )
    return _self_scene("two_bodies", surface, gap, thickness, element)


def _self_scene(name, surface, gap, thickness, element, **extra) -> Scene:
    """A self-contact scene: the surface is master and slave; params["d_max"] lies between
    the gap and the thickness (closer than the back side: detect_self's docstring)."""
    d_max = 0.5 * ((gap or 0.0) + thickness) if gap is not None else 0.8 * thickness
    return Scene(
        name,
        surface,
        surface.points[surface.nodes],
        surface,
        dict(
            n_nodes=len(surface.nodes),
            gap=gap,
            thickness=thickness,
            d_max=d_max,
            element=element,
            **extra,
        ),
    )


@dataclass(frozen=True, eq=False)
class Step:
    """A step of swept detection: the slaves move from slave_x0 to slave_x1 while the master
    (at its points) moves to master_x1 (detect_swept's inputs)."""

    name: str
    master: Surface
    master_x1: np.ndarray
    slave_x0: np.ndarray
    slave_x1: np.ndarray
    slave_surface: Surface | None = None
    params: dict = field(default_factory=dict)


def closing_step(scene: Scene, *, closing=1.6, jitter=0.1, seed=0) -> Step:
    """A step of a two-surface scene whose master faces +z and slave surface -z (rough,
    steep, graded): each body moves towards the other by closing / 2 times the scene's gap,
    and every node sideways by a random `jitter`, both in units of the local element size (the
    mean edge length around the node), so that a graded scene closes alike everywhere; with
    the default closing most slaves cross the master mid-step."""
    from ._surface import mesh_sizes

    rng = np.random.default_rng(seed + 7)
    gap = float(scene.params.get("gap", 1.0))
    m, s = scene.master, scene.slave_surface
    hm = mesh_sizes(m.element, m.faces, m.points)[1][:, None]
    hs = mesh_sizes(s.element, s.faces, s.points)[1][s.nodes][:, None]
    up = np.array([0.0, 0.0, 0.5 * closing * gap])
    side = np.array([1.0, 1.0, 0.0])
    m1 = m.points + hm * (up + rng.normal(0, jitter, m.points.shape) * side)
    x0 = scene.slave
    x1 = x0 + hs * (-up + rng.normal(0, jitter, x0.shape) * side)
    params = dict(scene.params, closing=closing, jitter=jitter)
    return Step(scene.name + "_closing", m, m1, x0, x1, s, params)


def closing_rough_surfaces(
    n_nodes=2**12, *, gap=1.0, closing=1.6, jitter=0.1, element="tri3", seed=0
) -> Step:
    """Rough surfaces `gap` apart (rough_surfaces) that close by `closing` within the step
    (closing_step)."""
    sc = rough_surfaces(n_nodes, gap=gap, element=element, seed=seed)
    return closing_step(sc, closing=closing, jitter=jitter, seed=seed)


def rolling_tyre(
    n_nodes=2**12, *, radius=20.0, lift=0.3, drop=0.8, turn=0.05, element="tri3", seed=0
) -> Step:
    """A tyre (cylinder_on_road's slave nodes) `lift` above a rough road, rolling over the
    step: it turns by `turn` radians about its axis, advances by radius * turn and sinks by
    `drop`, so the nodes near the bottom reach the road at different times; the road is
    still."""
    sc = cylinder_on_road(n_nodes, radius=radius, depth=-lift, element=element, seed=seed)
    x0 = sc.slave
    top = sc.master.points[:, 2].max()
    centre = np.array([0.0, 0.0, top + lift + radius])
    c, s = np.cos(turn), np.sin(turn)
    rot = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    x1 = (x0 - centre) @ rot.T + centre + [radius * turn, 0, -drop]
    params = dict(sc.params, lift=lift, drop=drop, turn=turn)
    return Step("rolling_tyre", sc.master, sc.master.points.copy(), x0, x1, None, params)
