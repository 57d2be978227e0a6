"""Triangle meshes as plain numpy arrays, and the closed primitives the world is made of.

Everything SynthCars casts rays against is a union of *closed, outward-oriented*
components (every edge shared by exactly two triangles with opposite orientation), so
that inside/outside is well defined per component: the shape sampler uses that to drop
surface samples hidden inside another component (a wheel inside an arch, a bed rail
inside the body). Components are kept apart (``component`` per triangle) instead of
being merged by CSG, which nothing here needs: the ray caster takes the first hit.

A per-triangle ``material`` code drives the sensor model (glass drops returns, tyres
are dark); see :data:`MATERIALS`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# material code -> (name, albedo, extra dropout probability)
MATERIALS: dict[int, tuple[str, float, float]] = {
    0: ("paint", 0.45, 0.0),
    1: ("glass", 0.08, 0.55),
    2: ("tyre", 0.05, 0.05),
    3: ("asphalt", 0.22, 0.0),
    4: ("concrete", 0.35, 0.0),
    5: ("vegetation", 0.30, 0.08),
    6: ("metal", 0.55, 0.0),
    7: ("clothing", 0.25, 0.0),
}
PAINT, GLASS, TYRE, ASPHALT, CONCRETE, VEGETATION, METAL, CLOTHING = range(8)


@dataclass
class Mesh:
    """A triangle soup made of closed components.

    Attributes:
        vertices: ``(V, 3)`` float64.
        triangles: ``(T, 3)`` int64 vertex indices, counter-clockwise seen from outside.
        material: ``(T,)`` int8 material code per triangle.
        component: ``(T,)`` int32 index of the closed component a triangle belongs to.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    material: np.ndarray
    component: np.ndarray

    @property
    def n_components(self) -> int:
        return int(self.component.max()) + 1 if len(self.component) else 0

    def transformed(self, rotation: np.ndarray, translation: np.ndarray) -> Mesh:
        """Rigid (or scaled) copy: ``v @ R.T + t``; topology arrays are shared."""
        return Mesh(self.vertices @ np.asarray(rotation).T + translation, self.triangles, self.material, self.component)

    def component_mesh(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """Vertices and triangles (re-indexed) of one closed component."""
        tris = self.triangles[self.component == index]
        used, inverse = np.unique(tris, return_inverse=True)
        return self.vertices[used], inverse.reshape(-1, 3)

    def area(self) -> np.ndarray:
        """``(T,)`` triangle areas."""
        v = self.vertices[self.triangles]
        return 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)


def concatenate(meshes: list[Mesh]) -> Mesh:
    """One mesh from several; component indices are renumbered to stay distinct."""
    verts, tris, mats, comps = [], [], [], []
    v_off = c_off = 0
    for m in meshes:
        verts.append(m.vertices)
        tris.append(m.triangles + v_off)
        mats.append(m.material)
        comps.append(m.component + c_off)
        v_off += len(m.vertices)
        c_off += m.n_components
    return Mesh(
        np.concatenate(verts) if verts else np.zeros((0, 3)),
        np.concatenate(tris) if tris else np.zeros((0, 3), np.int64),
        np.concatenate(mats) if mats else np.zeros(0, np.int8),
        np.concatenate(comps) if comps else np.zeros(0, np.int32),
    )


def _single(vertices: np.ndarray, triangles: np.ndarray, material: int) -> Mesh:
    t = np.asarray(triangles, dtype=np.int64)
    return Mesh(
        np.asarray(vertices, dtype=np.float64), t, np.full(len(t), material, np.int8), np.zeros(len(t), np.int32)
    )


def tube(rings: np.ndarray, material: np.ndarray | int = PAINT) -> Mesh:
    """Closed mesh lofted through ``(S, K, 3)`` rings, capped by fans at both ends.

    Rings must run counter-clockwise when seen from the ``-x`` end looking toward ``+x``
    (i.e. positive orientation in the (y, z) plane) and stations must increase along x,
    which makes every face point outward. ``material`` may be per quad, ``(S-1, K)``.
    """
    s, k, _ = rings.shape
    verts = rings.reshape(-1, 3)
    idx = np.arange(s * k).reshape(s, k)
    a = idx[:-1, :]
    b = idx[:-1, np.r_[1:k, 0]]
    c = idx[1:, np.r_[1:k, 0]]
    d = idx[1:, :]
    # Quad a(i,j) b(i,j+1) c(i+1,j+1) d(i+1,j): outward when rings are CCW in (y,z) and x grows.
    side = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    quad_mat = np.broadcast_to(np.asarray(material, dtype=np.int8), (s - 1, k)).reshape(-1)
    side_mat = np.concatenate([quad_mat, quad_mat])
    c0, c1 = len(verts), len(verts) + 1
    centres = np.stack([rings[0].mean(0), rings[-1].mean(0)])
    j = np.arange(k)
    jn = np.r_[1:k, 0]
    cap0 = np.stack([np.full(k, c0), idx[0, jn], idx[0, j]], -1)  # faces -x
    cap1 = np.stack([np.full(k, c1), idx[-1, j], idx[-1, jn]], -1)  # faces +x
    tris = np.concatenate([side, cap0, cap1])
    mat = np.concatenate([side_mat, np.full(k, quad_mat[0]), np.full(k, quad_mat[-1])]).astype(np.int8)
    return Mesh(np.concatenate([verts, centres]), tris, mat, np.zeros(len(tris), np.int32))


def box(size: np.ndarray, center: np.ndarray = (0.0, 0.0, 0.0), material: int = CONCRETE) -> Mesh:
    """Axis-aligned closed box (12 triangles)."""
    sx, sy, sz = np.asarray(size, dtype=np.float64) / 2.0
    v = np.array([[x, y, z] for x in (-sx, sx) for y in (-sy, sy) for z in (-sz, sz)]) + np.asarray(center)
    # vertex index = 4*ix + 2*iy + iz
    t = [
        [0, 1, 3], [0, 3, 2],  # -x
        [4, 6, 7], [4, 7, 5],  # +x
        [0, 4, 5], [0, 5, 1],  # -y
        [2, 3, 7], [2, 7, 6],  # +y
        [0, 2, 6], [0, 6, 4],  # -z
        [1, 5, 7], [1, 7, 3],  # +z
    ]
    return _single(v, t, material)


def cylinder(radius: float, height: float, segments: int = 16, material: int = METAL) -> Mesh:
    """Closed cylinder about +z, base at z=0, top at z=height."""
    ang = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    ring = np.stack([radius * np.cos(ang), radius * np.sin(ang)], -1)
    # Loft along x then rotate x->z: build rings in the (y, z) plane, CCW.
    rings = np.stack([np.c_[np.full(segments, x), ring] for x in (0.0, height)])
    m = tube(rings, material)
    # Map (x, y, z) -> (y, z, x): a proper rotation (cyclic permutation), x becomes z.
    rot = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    return m.transformed(rot, np.zeros(3))


def sphere(radius: np.ndarray | float, center=(0.0, 0.0, 0.0), subdivisions: int = 2, material: int = VEGETATION,
           rng: np.random.Generator | None = None, roughness: float = 0.0) -> Mesh:
    """Icosphere (optionally an ellipsoid via a 3-vector radius, roughened into a blob)."""
    v, t = _icosphere(subdivisions)
    if rng is not None and roughness > 0:
        # Low-frequency bumps: a few random cosine lobes, smooth so the blob stays star-shaped.
        dirs = rng.normal(size=(6, 3))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        amp = rng.uniform(-roughness, roughness, 6)
        scale = 1.0 + (np.maximum(v @ dirs.T, 0.0) ** 2 * amp).sum(1)
        v = v * scale[:, None]
    return _single(v * np.asarray(radius) + np.asarray(center, dtype=np.float64), t, material)


_ICO_CACHE: dict[int, tuple[np.ndarray, np.ndarray]] = {}


def _icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    if subdivisions in _ICO_CACHE:
        return _ICO_CACHE[subdivisions]
    p = (1 + 5**0.5) / 2
    v = np.array([[-1, p, 0], [1, p, 0], [-1, -p, 0], [1, -p, 0], [0, -1, p], [0, 1, p],
                  [0, -1, -p], [0, 1, -p], [p, 0, -1], [p, 0, 1], [-p, 0, -1], [-p, 0, 1]], dtype=np.float64)
    t = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
                  [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
                  [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]], dtype=np.int64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(subdivisions):
        edges = np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1)
        uniq, inv = np.unique(edges, axis=0, return_inverse=True)
        mid = v[uniq].mean(1)
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = inv.reshape(3, -1).T + len(v)  # midpoints of edges (01, 12, 20) per triangle
        v = np.concatenate([v, mid])
        a, b, c = t.T
        ab, bc, ca = m.T
        t = np.concatenate([np.stack(x, 1) for x in ([a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca])])
    _ICO_CACHE[subdivisions] = (v, t)
    return v, t


def is_closed_oriented(vertices: np.ndarray, triangles: np.ndarray) -> bool:
    """Every directed edge appears once and its reverse once (closed, consistently oriented),
    and the enclosed signed volume is positive (normals point outward)."""
    e = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    directed = np.unique(e, axis=0)
    if len(directed) != len(e):
        return False
    fwd = e[:, 0] * (len(vertices) + 1) + e[:, 1]
    rev = e[:, 1] * (len(vertices) + 1) + e[:, 0]
    if not np.array_equal(np.sort(fwd), np.sort(rev)):
        return False
    v = vertices[triangles]
    volume = np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0
    return bool(volume > 0)


def sample_surface(mesh: Mesh, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points uniformly by area; also returns the triangle index of each point."""
    area = mesh.area()
    tri = rng.choice(len(area), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], 1)
    v = mesh.vertices[mesh.triangles[tri]]
    return np.einsum("nk,nkj->nj", w, v), tri
