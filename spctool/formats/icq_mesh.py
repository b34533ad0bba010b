"""ICQ shapes <-> triangle meshes (spc-formats.md §5.2, §10).

:func:`icq_to_mesh` turns an :class:`~spctool.formats.icq.IcqShape` into a
:class:`~spctool.formats.mesh.TriangleMesh` (two outward triangles per cell, seams merged);
:func:`mesh_to_icq` recognises a mesh whose vertex list is an ICQ grid (the OSIRIS-REx Bennu OBJ
files, Gaskell's SBMT VTK shapes) and gives the ICQ shape back.  Kept apart from both file modules
because :mod:`spctool.formats.mesh` reads any shape file, ICQ included (it imports
:mod:`spctool.formats.icq`), so the ICQ module cannot import the mesh module back.
"""

from __future__ import annotations

import math

import numpy as np

from spctool.errors import SpcFormatError
from spctool.formats.icq import IcqShape, _seam_pairs_cached, icq_merge_map, icq_triangles, unify_seams
from spctool.formats.mesh import TriangleMesh

__all__ = ["icq_to_mesh", "mesh_to_icq"]


def icq_to_mesh(shape: IcqShape, *, compact: bool = False) -> TriangleMesh:
    """Triangle mesh of ``shape`` with merged seams and outward normals (§5.2).

    Two triangles per quad, (I,J),(I,J+1),(I+1,J) and (I+1,J),(I,J+1),(I+1,J+1).
    By default the vertex list is the full ICQ list in file order (like the Bennu
    OBJ files), with the triangles referencing only the 6Q² + 2 seam
    representatives, so :func:`mesh_to_icq` gives the shape back.  ``compact=True``
    keeps only the representatives (renumbered in file order).  Albedo is dropped.
    """
    faces = icq_triangles(shape.q, merged=True)
    vertices = shape.flat_vertices().copy()
    if compact:
        keep = np.unique(icq_merge_map(shape.q))
        renum = np.full(vertices.shape[0], -1, dtype=np.int64)
        renum[keep] = np.arange(keep.size)
        vertices = vertices[keep]
        faces = renum[faces]
    comments = [f" ICQ shape, Q = {shape.q}" + (f", from {shape.path}" if shape.path else "")]
    return TriangleMesh(vertices, faces, None, comments, path=shape.path)


def mesh_to_icq(mesh: TriangleMesh, *, seam_tolerance: float = 0.0) -> IcqShape:
    """The ICQ shape whose vertex list is ``mesh.vertices`` (6(Q+1)² vertices in ICQ order).

    The vertex count must be 6(Q+1)² and the 12 seam identities of §5.2 must
    hold bit-exactly (the real Bennu OBJ files do); otherwise the vertex list
    is not an ICQ grid and :class:`SpcFormatError` says why.  With
    ``seam_tolerance > 0`` (km) duplicates within the tolerance are accepted and
    unified to their representative (e.g. the Gaskell VTK shapes, whose seam
    duplicates differ by up to a few metres).  The faces are not used.
    """
    where = mesh.path
    v = np.asarray(mesh.vertices, dtype=np.float64)
    nv = v.shape[0]
    n = math.isqrt(nv // 6)
    if nv % 6 or n * n * 6 != nv or n < 2:
        raise SpcFormatError(
            where, None, f"expected 6(Q+1)² vertices for an ICQ grid (e.g. 6534 for Q = 32), found {nv}"
        )
    q = n - 1
    pairs = _seam_pairs_cached(q)
    diff = np.max(np.abs(v[pairs[:, 0]] - v[pairs[:, 1]]), axis=1)
    bad = diff > seam_tolerance if seam_tolerance > 0 else diff != 0
    if bad.any():
        a, b = pairs[np.flatnonzero(bad)[0]].tolist()
        raise SpcFormatError(
            where,
            None,
            f"expected the vertex list of an ICQ grid (Q = {q}) in ICQ order with identical seam duplicates; "
            f"{int(bad.sum())} of {len(pairs)} seam pairs differ (up to {float(diff.max()):.3g} km), e.g. "
            f"vertices {a + 1} and {b + 1} (1-based): the vertices are not in ICQ order, or the seam "
            "duplicates were not written identically"
            + ("" if seam_tolerance > 0 else " (pass seam_tolerance= to accept near-identical seams)"),
        )
    shape = IcqShape(q, v.reshape(6, n, n, 3).copy(), None, where)
    if seam_tolerance > 0 and diff.any():
        shape = unify_seams(shape)
    return shape
