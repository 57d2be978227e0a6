"""Decoded SDF grids to surfaces: batched marching cubes and area-uniform point sampling.

The whole batch goes through one marching-cubes call (grids stacked along the height axis,
each wrapped in a layer of "outside"), and the points of every mesh are drawn in one
vectorised pass seeded per instance.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from pcc_ros.geometry.voxels import AML_GRID, GridSpec, from_box_frame


def _stacked_marching_cubes(sdf: np.ndarray, spec: GridSpec, level: float, allow_degenerate: bool
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One marching-cubes call on a batch of SDF grids stacked along the height axis, each
    wrapped in a one-voxel layer of "outside" (meshes closed at the grid border, no triangle
    joining two instances). Returns grid-frame vertices ``(V, 3)``, faces ``(F, 3)`` (global
    vertex indices) and each vertex's instance; empty arrays when nothing crosses ``level``."""
    from skimage.measure import marching_cubes

    b, h, n, w = sdf.shape
    outside = float(max(np.abs(sdf).max(), 1.0)) if sdf.size else 1.0
    padded = np.full((b, h + 2, n + 2, w + 2), outside, dtype=np.float32)
    padded[:, 1:-1, 1:-1, 1:-1] = sdf
    volume = padded.reshape(b * (h + 2), n + 2, w + 2)
    if not (volume.min() < level < volume.max()):
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
    verts, faces, _, _ = marching_cubes(volume, level=level, method="lewiner", allow_degenerate=allow_degenerate)
    owner = np.floor(verts[:, 0] / (h + 2)).astype(np.int64)
    local = verts - np.stack([owner * (h + 2) + 1, np.ones_like(owner), np.ones_like(owner)], axis=1)
    return spec.from_hlw(local), faces.astype(np.int64), owner


def marching_cubes_batch(sdf: np.ndarray, spec: GridSpec = AML_GRID, level: float = 0.0
                         ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Meshes of the zero level sets of a batch of SDF grids, in one marching-cubes call
    (:func:`_stacked_marching_cubes`; degenerate triangles removed).

    Returns:
        per instance ``(vertices (V, 3) in the grid's frame float64, faces (F, 3) int64)``; an
        instance without a surface gets empty arrays.
    """
    b = len(sdf)
    canonical, faces, owner = _stacked_marching_cubes(sdf, spec, level, allow_degenerate=False)
    empty = (np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    if len(faces) == 0:
        return [empty] * b
    face_owner = owner[faces[:, 0]]
    order = np.argsort(face_owner, kind="stable")
    faces, face_owner = faces[order], face_owner[order]
    v_counts = np.bincount(owner, minlength=b)
    v_start = np.cumsum(v_counts) - v_counts
    v_order = np.argsort(owner, kind="stable")  # vertices are emitted block by block; be sure
    rank = np.empty_like(v_order)
    rank[v_order] = np.arange(len(v_order))
    f_bounds = np.searchsorted(face_owner, np.arange(b + 1))
    out = []
    for i in range(b):  # split per instance (slicing only)
        if v_counts[i] == 0:
            out.append(empty)
            continue
        f = rank[faces[f_bounds[i]:f_bounds[i + 1]]] - v_start[i]
        out.append((canonical[v_order[v_start[i]:v_start[i] + v_counts[i]]], f.astype(np.int64)))
    return out


def _sample_faces(verts: np.ndarray, faces: np.ndarray, face_owner: np.ndarray, count: int, n: int,
                  seeds: Sequence[int]) -> list[np.ndarray]:
    """``n`` points uniform by area on the faces of each of ``count`` instances (faces of all
    instances in one array, ``face_owner`` their instance); the draws of an instance depend
    only on its seed. An instance without faces (or area) gets an empty array."""
    if len(faces) == 0:
        return [np.zeros((0, 3), np.float32) for _ in range(count)]
    if (np.diff(face_owner) < 0).any():  # marching cubes emits them in order; be sure
        order = np.argsort(face_owner, kind="stable")
        faces, face_owner = faces[order], face_owner[order]
    a = verts[faces[:, 0]]
    e1 = verts[faces[:, 1]] - a
    e2 = verts[faces[:, 2]] - a
    cross = np.stack([e1[:, 1] * e2[:, 2] - e1[:, 2] * e2[:, 1], e1[:, 2] * e2[:, 0] - e1[:, 0] * e2[:, 2],
                      e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]], axis=1)
    area = 0.5 * np.sqrt(np.einsum("ij,ij->i", cross, cross))
    cum = np.cumsum(area)
    total = np.bincount(face_owner, weights=area, minlength=count)
    start = np.concatenate([[0.0], cum])[np.searchsorted(face_owner, np.arange(count))]
    u = np.stack([np.random.default_rng(s).random((n, 3)) for s in seeds])  # (B, n, 3)
    face = np.clip(np.searchsorted(cum, start[:, None] + u[..., 0] * total[:, None], side="right"), 0, len(cum) - 1)
    r1 = np.sqrt(u[..., 1:2])
    points = (a[face] + r1 * (1 - u[..., 2:3]) * e1[face] + r1 * u[..., 2:3] * e2[face]).astype(np.float32)
    return [points[i] if total[i] > 0 else np.zeros((0, 3), np.float32) for i in range(count)]


def sample_meshes(meshes: Sequence[tuple[np.ndarray, np.ndarray]], n: int, seeds: Sequence[int]) -> list[np.ndarray]:
    """``n`` points uniform by area on each mesh, all meshes in one vectorised pass.

    ``seeds``: one per mesh (the draws of a mesh depend only on its seed). A mesh without
    faces gives an empty array.
    """
    if not meshes:
        return []
    sizes = np.array([len(v) for v, _ in meshes])
    offsets = np.cumsum(sizes) - sizes
    verts = np.concatenate([np.asarray(v, np.float64).reshape(-1, 3) for v, _ in meshes])
    faces = np.concatenate([np.asarray(f, np.int64).reshape(-1, 3) + o for (_, f), o in zip(meshes, offsets)])
    owner = np.repeat(np.arange(len(meshes)), [len(f) for _, f in meshes])
    return _sample_faces(verts, faces, owner, len(meshes), n, seeds)


def surface_samples(sdf: np.ndarray, spec: GridSpec, aspects: np.ndarray, n: int, seeds: Sequence[int],
                    level: float = 0.0) -> list[np.ndarray]:
    """Decoded SDF grids -> ``n`` canonical points uniform by area on each zero level set: one
    marching-cubes call for the batch, each mesh stretched from the grid's frame by its
    ``aspects`` row, sampled without splitting the batch into meshes. Degenerate (zero-area)
    triangles are kept: they are never drawn."""
    verts, faces, owner = _stacked_marching_cubes(sdf, spec, level, allow_degenerate=True)
    if len(faces) == 0:
        return [np.zeros((0, 3), np.float32) for _ in range(len(sdf))]
    return _sample_faces(from_box_frame(verts, np.asarray(aspects, np.float64)[owner]), faces, owner[faces[:, 0]],
                         len(sdf), n, seeds)
