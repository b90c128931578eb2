"""Contact surfaces from volume and surface meshes, and through meshio's file formats."""

import meshio
import numpy as np
import pytest

import arraycontact as ac
from arraycontact._elements import interpolate

HEX_CORNERS = [
    (0, 0, 0),
    (1, 0, 0),
    (1, 1, 0),
    (0, 1, 0),
    (0, 0, 1),
    (1, 0, 1),
    (1, 1, 1),
    (0, 1, 1),
]
KUHN = [(0, 1, 2, 6), (0, 2, 3, 6), (0, 3, 7, 6), (0, 7, 4, 6), (0, 4, 5, 6), (0, 5, 1, 6)]


def hex_block(n=3, size=2.0):
    """n^3 hexahedra filling the cube [0, size]^3 (VTK node order)."""
    g = np.arange(n + 1)
    idx = lambda i, j, k: (i * (n + 1) + j) * (n + 1) + k  # noqa: E731
    pts = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3) * size / n
    cells = [
        [idx(i + a, j + b, k + c) for a, b, c in HEX_CORNERS]
        for i in range(n)
        for j in range(n)
        for k in range(n)
    ]
    return pts.astype(float), np.array(cells)


def tet_cube(n=3, size=2.0):
    pts, hexes = hex_block(n, size)
    return pts, hexes[:, KUHN].reshape(-1, 4)


def add_mid_nodes(pts, cells, edges, faces=(), centre=False):
    """Quadratic cells: a shared node at the middle of every edge (and face, and cell)."""
    pts = list(map(tuple, pts))
    where = {}

    def node(ids):
        key = tuple(sorted(ids))
        if key not in where:
            where[key] = len(pts)
            pts.append(tuple(np.mean([pts[i] for i in ids], 0)))
        return where[key]

    out = []
    for c in cells:
        row = list(c) + [node((c[a], c[b])) for a, b in edges]
        row += [node(tuple(c[i] for i in f)) for f in faces]
        if centre:
            row.append(node(tuple(c)))
        out.append(row)
    return np.array(pts, float), np.array(out)


TET10_EDGES = [(0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3)]
HEX20_EDGES = [
    (0, 1),
    (1, 2),
    (2, 3),
    (3, 0),
    (4, 5),
    (5, 6),
    (6, 7),
    (7, 4),
    (0, 4),
    (1, 5),
    (2, 6),
    (3, 7),
]
HEX27_FACES = [(0, 3, 7, 4), (1, 2, 6, 5), (0, 1, 5, 4), (3, 2, 6, 7), (0, 1, 2, 3), (4, 5, 6, 7)]


def _quadrature(e):
    if e.kind == "tri":
        return np.array([[1, 1], [4, 1], [1, 4]]) / 6.0, np.full(3, 1 / 6)
    g = 1 / np.sqrt(3)
    return np.array([[-g, -g], [g, -g], [g, g], [-g, g]]), np.ones(4)


def area_and_volume(s):
    """Area and enclosed volume (divergence theorem: V = 1/3 of the integral of x.n dA)."""
    xi, w = _quadrature(s.element)
    xe = s.points[s.faces]
    area = vol = 0.0
    for q, wq in zip(xi, w):
        x, dx = interpolate(s.element, xe, np.broadcast_to(q, (len(xe), 2)))
        nda = np.cross(dx[..., 0], dx[..., 1])
        area += wq * np.linalg.norm(nda, axis=1).sum()
        vol += wq * np.einsum("ij,ij->i", x, nda).sum() / 3
    return area, vol


def check_mid_nodes(s):
    """Each mid node is the middle of its edge and a centre node the face's centre."""
    e = s.element
    x = s.points[s.faces]
    for a, b, *mid in e.edge_nodes:
        if mid:
            assert np.allclose(x[:, mid[0]], (x[:, a] + x[:, b]) / 2)
    if e.nodes_per_face == 9:
        assert np.allclose(x[:, 8], x[:, :4].mean(1))


@pytest.mark.parametrize(
    "cell_type, make, element, n_faces",
    [
        ("hexahedron", lambda: hex_block(3), "quad4", 54),
        ("tetra", lambda: tet_cube(3), "tri3", 108),
        ("tetra10", lambda: add_mid_nodes(*tet_cube(2), TET10_EDGES), "tri6", 48),
        ("hexahedron20", lambda: add_mid_nodes(*hex_block(2), HEX20_EDGES), "quad8", 24),
        (
            "hexahedron27",
            lambda: add_mid_nodes(*hex_block(2), HEX20_EDGES, HEX27_FACES, True),
            "quad9",
            24,
        ),
    ],
)
def test_exterior_of_volume_meshes(cell_type, make, element, n_faces):
    pts, cells = make()
    s = ac.surface_from_meshio(meshio.Mesh(pts, [(cell_type, cells)]))
    assert s.element.name == element and s.n_faces == n_faces and s.closed
    area, vol = area_and_volume(s)
    assert area == pytest.approx(24.0) and vol == pytest.approx(8.0)  # outward everywhere
    check_mid_nodes(s)
    # Global numbering: the surface's node ids are the mesh's ids of the boundary nodes.
    on_boundary = ((pts[s.nodes] == 0) | (pts[s.nodes] == 2.0)).any(1)
    assert on_boundary.all()
    assert len(s.nodes) == ((pts == 0) | (pts == 2.0)).any(1).sum()


def test_wedges_need_an_element_choice():
    pts, hexes = hex_block(2)
    # Split every hex into two wedges along the x-y diagonal (triangles 0,1,2 / 0,2,3).
    w = np.r_[hexes[:, [0, 1, 2, 4, 5, 6]], hexes[:, [0, 2, 3, 4, 6, 7]]]
    mesh = meshio.Mesh(pts, [("wedge", w)])
    with pytest.raises(ValueError, match="mixes face types"):
        ac.surface_from_meshio(mesh)
    tri = ac.surface_from_meshio(mesh, element="tri3")
    quad = ac.surface_from_meshio(mesh, element="quad4")
    assert tri.n_faces == 16 and quad.n_faces == 16
    assert (tri.face_normals[:, 2] ** 2 == 1).all()  # top and bottom
    a1, v1 = area_and_volume(tri)
    a2, v2 = area_and_volume(quad)
    assert a1 + a2 == pytest.approx(24.0) and v1 + v2 == pytest.approx(8.0)


def test_surface_cells_and_selection():
    pts, hexes = hex_block(2)
    tris = np.array([[0, 1, 3]])
    mesh = meshio.Mesh(
        pts,
        [("hexahedron", hexes), ("triangle", tris)],
        cell_sets={
            "top": [np.array([1, 3]), np.array([], int)],
            "skin": [np.array([], int), np.array([0])],
        },
    )
    assert ac.surface_from_meshio(mesh, cell_blocks="triangle").n_faces == 1
    assert ac.surface_from_meshio(mesh, cell_blocks=[0]).n_faces == 24
    assert ac.surface_from_meshio(mesh, cell_set="skin").element.name == "tri3"
    assert ac.surface_from_meshio(mesh, cell_set="top").n_faces == 10  # 2 hexes: 12 - 2 shared
    with pytest.raises(ValueError, match="mixes face types"):
        ac.surface_from_meshio(mesh)
    with pytest.raises(ValueError, match="no cell set"):
        ac.surface_from_meshio(mesh, cell_set="nope")
    with pytest.raises(ValueError, match="no gmsh physical"):
        ac.surface_from_meshio(mesh, physical="x")
    with pytest.raises(ValueError, match="out of range"):
        ac.surface_from_meshio(mesh, cell_blocks=[5])


def _two_bodies():
    """A hex block (physical 'block') and a triangle patch (physical 'patch') above it."""
    pts, hexes = hex_block(2)
    top = np.array([[0, 0, 3.0], [2, 0, 3], [2, 2, 3], [0, 2, 3]])
    pts = np.r_[pts, top]
    k = len(pts) - 4
    tris = np.array([[k, k + 1, k + 2], [k, k + 2, k + 3]])
    cells = [("hexahedron", hexes), ("triangle", tris)]
    tags = [np.full(len(hexes), 1), np.full(2, 2)]
    return meshio.Mesh(
        pts,
        cells,
        cell_data={"gmsh:physical": tags, "gmsh:geometrical": tags},
        field_data={"block": np.array([1, 3]), "patch": np.array([2, 2])},
    )


def test_gmsh_round_trip(tmp_path):
    path = tmp_path / "bodies.msh"
    meshio.write(path, _two_bodies(), file_format="gmsh22", binary=False)
    block = ac.read_surface(path, physical="block")
    patch = ac.read_surface(path, physical="patch")
    assert block.n_faces == 24 and patch.n_faces == 2 and block.closed
    assert ac.read_surface(path, physical=2).n_faces == 2
    # Ids are the file's: the patch's slaves keep their node numbers.
    c = ac.detect(patch, block, d_max=1.5, backend="numpy")
    assert set(c.slave_ids) == set(patch.nodes) and c.active.all()
    assert np.allclose(c.gap, 1.0)
    with pytest.raises(ValueError, match="no physical group"):
        ac.read_surface(path, physical="nope")


def test_vtu_round_trip(tmp_path):
    pts, tets = tet_cube(2)
    path = tmp_path / "cube.vtu"
    meshio.write(path, meshio.Mesh(pts, [("tetra", tets)]))
    s = ac.read_surface(path)
    assert s.n_faces == 48 and area_and_volume(s)[1] == pytest.approx(8.0)


def test_abaqus_round_trip(tmp_path):
    pts, hexes = hex_block(2)
    mesh = meshio.Mesh(pts, [("hexahedron", hexes)], cell_sets={"LEFT": [np.array([0, 1, 2, 3])]})
    path = tmp_path / "block.inp"
    meshio.write(path, mesh)
    assert ac.read_surface(path).n_faces == 24
    left = ac.read_surface(path, cell_set="LEFT")
    assert left.n_faces == 16 and area_and_volume(left)[1] == pytest.approx(4.0)
