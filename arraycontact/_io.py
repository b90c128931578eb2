"""Contact surfaces from meshes (seed 004, automatic identification of contact surfaces).

Surface cells are used as they are. Volume cells give their exterior faces: every face of every
cell gets a key (its sorted corner ids); after a sort, a key that occurs once is a face on the
exterior. Each exterior face is oriented outward, away from the centroid of the cell it bounds.
Node ids stay the mesh's ids, so slave and master ids are the mesh's node numbers.
"""

from __future__ import annotations

import numpy as np

from ._surface import Surface

# Surface cell types of meshio -> element names.
_SURFACE_CELLS = {
    "triangle": "tri3",
    "quad": "quad4",
    "triangle6": "tri6",
    "quad8": "quad8",
    "quad9": "quad9",
}

# Volume cells: faces as corner cycles (any orientation: they are oriented geometrically), the
# mid-edge node of each corner pair and the centre node of each face (VTK / meshio numbering).
_TET = [(0, 1, 2), (0, 1, 3), (1, 2, 3), (0, 2, 3)]
_HEX = [(0, 1, 2, 3), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)]
_WEDGE = [(0, 1, 2), (3, 4, 5), (0, 1, 4, 3), (1, 2, 5, 4), (2, 0, 3, 5)]
_TET10_MID = {(0, 1): 4, (1, 2): 5, (0, 2): 6, (0, 3): 7, (1, 3): 8, (2, 3): 9}
_HEX20_MID = {
    (0, 1): 8,
    (1, 2): 9,
    (2, 3): 10,
    (0, 3): 11,
    (4, 5): 12,
    (5, 6): 13,
    (6, 7): 14,
    (4, 7): 15,
    (0, 4): 16,
    (1, 5): 17,
    (2, 6): 18,
    (3, 7): 19,
}
_HEX27_CENTRE = {
    (0, 3, 4, 7): 20,
    (1, 2, 5, 6): 21,
    (0, 1, 4, 5): 22,
    (2, 3, 6, 7): 23,
    (0, 1, 2, 3): 24,
    (4, 5, 6, 7): 25,
}
_VOLUME_CELLS = {
    "tetra": (_TET, None, None),
    "tetra10": (_TET, _TET10_MID, None),
    "hexahedron": (_HEX, None, None),
    "hexahedron20": (_HEX, _HEX20_MID, None),
    "hexahedron27": (_HEX, _HEX20_MID, _HEX27_CENTRE),
    "wedge": (_WEDGE, None, None),
}
_FACE_ELEMENT = {
    (3, False, False): "tri3",
    (4, False, False): "quad4",
    (3, True, False): "tri6",
    (4, True, False): "quad8",
    (4, True, True): "quad9",
}


def _local_face(cycle, mid, centre):
    """Element-ordered local node ids of a face from its corner cycle."""
    k = len(cycle)
    nodes = list(cycle)
    if mid is not None:
        nodes += [mid[tuple(sorted((cycle[i], cycle[(i + 1) % k])))] for i in range(k)]
    if centre is not None:
        nodes.append(centre[tuple(sorted(cycle))])
    return nodes


def _cell_faces(cell_type, cells):
    """All faces of volume cells, grouped by element: {element: (faces, owner cell ids)}."""
    cycles, mid, centre = _VOLUME_CELLS[cell_type]
    out = {}
    for cyc in cycles:
        fwd = _local_face(cyc, mid, centre)
        rev = _local_face((cyc[0],) + tuple(reversed(cyc[1:])), mid, centre)
        name = _FACE_ELEMENT[(len(cyc), mid is not None, centre is not None)]
        out.setdefault(name, []).append((cells[:, fwd], cells[:, rev], np.arange(len(cells))))
    return out


def exterior_faces(points, cell_type, cells):
    """Exterior faces of volume cells, oriented outward: {element: faces}."""
    points = np.asarray(points, float)
    cells = np.asarray(cells, np.int64)
    groups = _cell_faces(cell_type, cells)
    corner_keys = []
    for name, parts in groups.items():
        k = 3 if name.startswith("tri") else 4
        for f_fwd, _, _ in parts:
            corner_keys.append(np.sort(f_fwd[:, :k], 1))
    # A face is exterior when its corner set occurs once among all faces of all cells. Triangle
    # and quad keys are padded to one width so that both kinds sort together.
    width = max(k.shape[1] for k in corner_keys)
    keys = np.concatenate(
        [np.pad(k, ((0, 0), (0, width - k.shape[1])), constant_values=-1) for k in corner_keys]
    )
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    once = counts[inverse.reshape(-1)] == 1
    centroid = points[cells].mean(1)
    out, start = {}, 0
    for name, parts in groups.items():
        sel = []
        k = 3 if name.startswith("tri") else 4
        for f_fwd, f_rev, owner in parts:
            m = once[start : start + len(f_fwd)]
            start += len(f_fwd)
            f, fr, o = f_fwd[m], f_rev[m], owner[m]
            x = points[f[:, :k]]
            # Newell normal of the corner polygon against the direction out of the cell.
            normal = np.cross(x, np.roll(x, -1, axis=1)).sum(1)
            outward = np.einsum("ij,ij->i", normal, x.mean(1) - centroid[o]) >= 0
            sel.append(np.where(outward[:, None], f, fr))
        out[name] = np.concatenate(sel)
    return {k: v for k, v in out.items() if len(v)}


def _selected_blocks(mesh, cell_blocks, cell_set, physical):
    """(cell type, cells) of the selected cells of a meshio mesh."""
    chosen = []
    masks = [None] * len(mesh.cells)
    if cell_set is not None:
        if cell_set not in mesh.cell_sets:
            raise ValueError(f"no cell set {cell_set!r}; the mesh has {sorted(mesh.cell_sets)}")
        for i, ids in enumerate(mesh.cell_sets[cell_set]):
            if ids is not None and len(ids):
                masks[i] = np.zeros(len(mesh.cells[i].data), bool)
                masks[i][np.asarray(ids, np.int64)] = True
            else:
                masks[i] = np.zeros(len(mesh.cells[i].data), bool)
    if physical is not None:
        tags = mesh.cell_data.get("gmsh:physical")
        if tags is None:
            raise ValueError("the mesh has no gmsh physical groups (cell data 'gmsh:physical')")
        tag = physical
        if isinstance(physical, str):
            if physical not in mesh.field_data:
                raise ValueError(
                    f"no physical group {physical!r}; the mesh has {sorted(mesh.field_data)}"
                )
            tag = int(mesh.field_data[physical][0])
        for i, t in enumerate(tags):
            m = np.asarray(t) == tag
            masks[i] = m if masks[i] is None else masks[i] & m
    if cell_blocks is not None:
        wanted = [cell_blocks] if isinstance(cell_blocks, (int, str)) else list(cell_blocks)
        for w in wanted:
            if isinstance(w, int) and not 0 <= w < len(mesh.cells):
                raise ValueError(f"cell block {w} out of range: the mesh has {len(mesh.cells)}")
        types = [c.type for c in mesh.cells]
        for w in wanted:
            if isinstance(w, str) and w not in types:
                raise ValueError(f"no cell block of type {w!r}; the mesh has {types}")
    for i, block in enumerate(mesh.cells):
        if cell_blocks is not None and i not in wanted and block.type not in wanted:
            continue
        data = np.asarray(block.data)
        if masks[i] is not None:
            data = data[masks[i]]
        if len(data):
            chosen.append((block.type, data))
    return chosen


def surface_from_meshio(mesh, *, cell_blocks=None, cell_set=None, physical=None, element=None):
    """Contact surface of a meshio mesh.

    Surface cells (triangle, quad, triangle6, quad8, quad9) are used as they are; volume cells
    (tetra, tetra10, hexahedron, hexahedron20, hexahedron27, wedge) give their exterior faces,
    oriented outward. Select cells by `cell_blocks` (indices or cell types), `cell_set` (a
    meshio cell set name) or `physical` (a gmsh physical group name or tag). Where the
    selection gives several face types (a wedge mesh has triangles and quads), `element` picks
    one. Node ids stay the mesh's."""
    groups = {}
    for cell_type, data in _selected_blocks(mesh, cell_blocks, cell_set, physical):
        if cell_type in _SURFACE_CELLS:
            groups.setdefault(_SURFACE_CELLS[cell_type], []).append(data)
        elif cell_type in _VOLUME_CELLS:
            for name, f in exterior_faces(mesh.points, cell_type, data).items():
                groups.setdefault(name, []).append(f)
        # Line and vertex cells carry no surface.
    if element is not None:
        if element not in groups:
            raise ValueError(f"the selection has no {element!r} faces; it has {sorted(groups)}")
        groups = {element: groups[element]}
    if len(groups) != 1:
        raise ValueError(
            "the selection gives no surface faces"
            if not groups
            else f"the selection mixes face types {sorted(groups)}: pick one with element="
        )
    ((name, parts),) = groups.items()
    points = np.asarray(mesh.points, float)
    if points.shape[1] == 2:
        points = np.c_[points, np.zeros(len(points))]
    return Surface(points, np.concatenate(parts), name)


def read_surface(
    path, *, cell_blocks=None, cell_set=None, physical=None, element=None, file_format=None
):
    """Read a mesh file with meshio and return its contact surface (see surface_from_meshio).
    A missing, unreadable or unknown file raises a ValueError that names it."""
    import contextlib
    import io
    import os

    import meshio

    if not os.path.isfile(path):
        raise ValueError(f"{path}: no such file")
    try:
        # meshio prints its own message and exits on some unreadable files: keep both.
        with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
            mesh = meshio.read(path, file_format=file_format)
    except SystemExit:
        raise ValueError(
            f"{path}: cannot read it as {file_format or 'the format its extension names'}"
        ) from None
    except meshio.ReadError as e:
        if "format" in str(e).lower() and file_format is None:
            raise ValueError(
                f"{path}: unknown mesh format; name it with file_format (the "
                f"command line's --format), one of meshio's formats such as "
                f"vtu, vtk, msh, xdmf, med, inp, obj, ply, stl"
            ) from None
        raise ValueError(f"{path}: cannot read it ({e})") from None
    except Exception as e:  # a parser failing inside meshio: the file is not what it claims
        raise ValueError(f"{path}: cannot read it as a mesh ({type(e).__name__}: {e})") from None
    try:
        return surface_from_meshio(
            mesh, cell_blocks=cell_blocks, cell_set=cell_set, physical=physical, element=element
        )
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None
