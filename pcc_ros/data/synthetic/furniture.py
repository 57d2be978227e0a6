"""Street furniture a car detector confuses with cars: bollards, signs, bicycles, fences.

Closed procedural meshes with real proportions (metres), built standing on z = 0 in their
own frame (x along the object), for :func:`pcc_ros.data.synthetic.scene.build_street` to place
on the sidewalk. Each is a union of closed primitives (:mod:`pcc_ros.data.synthetic.mesh`),
so the ray caster and the shape sampler treat them like every other object. Together with the
scene's pedestrians, poles, trees, bushes, vegetation blobs, low walls and bins they are the
non-vehicle world of SynthCars: the objects the simulated detector's *confusions* sit on
(:mod:`pcc_ros.data.synthetic.detector`).

Proportions: bollards 0.8-1.1 m tall, 0.16-0.24 m across (EN 12767 street bollards); traffic
signs a 2.0-2.6 m post with a 0.6-0.9 m plate; bicycles 1.65-1.85 m long, 1.0-1.1 m tall,
0.6 m across the handlebar, 0.68 m wheels; fences 1.0-1.8 m of posts every 2-2.5 m with two or
three rails (see-through, as mesh fences are to a LiDAR).
"""

from __future__ import annotations

import numpy as np

from pcc_ros.data.synthetic import mesh as M

#: Names of the furniture kinds this module builds (``SceneObject.name``).
FURNITURE = ("bollard", "sign", "bicycle", "fence")


def bollard(rng: np.random.Generator) -> M.Mesh:
    """A metal post with a dome cap."""
    r, h = float(rng.uniform(0.08, 0.12)), float(rng.uniform(0.8, 1.1))
    return M.concatenate([M.cylinder(r, h, 12, M.METAL), M.sphere(np.array([r, r, 0.5 * r]), [0, 0, h], 1, M.METAL)])


def sign(rng: np.random.Generator) -> M.Mesh:
    """A thin post carrying a flat plate (square or round) at its top."""
    post = float(rng.uniform(2.0, 2.6))
    plate = float(rng.uniform(0.6, 0.9))
    parts = [M.cylinder(0.035, post, 8, M.METAL)]
    if rng.random() < 0.5:
        parts.append(M.box([0.04, plate, plate], [0.0, 0.0, post - plate / 2], M.METAL))
    else:
        parts.append(M.sphere(np.array([0.02, plate / 2, plate / 2]), [0.0, 0.0, post - plate / 2], 2, M.METAL))
    return M.concatenate(parts)


def _wheel(radius: float, centre_x: float) -> M.Mesh:
    """A thin disc about the y axis (tyre and spokes seen as one solid disc) standing on z = 0."""
    disc = M.cylinder(radius, 0.05, 16, M.TYRE)  # axis +z, base at 0
    to_y = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # z -> -y: a proper rotation
    return disc.transformed(to_y, [centre_x, -0.025, radius])


def _bar(a: np.ndarray, b: np.ndarray, thickness: float) -> M.Mesh:
    """A square bar from ``a`` to ``b`` in the x-z plane (a frame tube)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    d = b - a
    length = float(np.linalg.norm(d))
    pitch = np.arctan2(d[2], d[0])
    c, s = np.cos(pitch), np.sin(pitch)
    rot = np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])
    return M.box([length, thickness, thickness], [0.0, 0.0, 0.0], M.METAL).transformed(rot, (a + b) / 2)


def bicycle(rng: np.random.Generator) -> M.Mesh:
    """Two wheels, a diamond frame, saddle and handlebar (parked, upright)."""
    wheel_r = float(rng.uniform(0.32, 0.35))
    base = float(rng.uniform(1.0, 1.1))  # wheelbase
    rear, front = -base / 2, base / 2
    hub = wheel_r
    seat = np.array([rear + 0.25, 0.0, hub + 0.55])
    head = np.array([front - 0.12, 0.0, hub + 0.5])
    crank = np.array([rear + 0.42, 0.0, hub - 0.05])
    parts = [
        _wheel(wheel_r, rear), _wheel(wheel_r, front),
        _bar([rear, 0, hub], crank, 0.035), _bar([rear, 0, hub], seat, 0.03), _bar(crank, seat, 0.04),
        _bar(crank, head, 0.045), _bar(seat, head, 0.04), _bar(head, [front, 0, hub], 0.035),
        M.box([0.25, 0.14, 0.06], seat + np.array([0.0, 0.0, 0.12]), M.CLOTHING),  # saddle
        M.box([0.05, 0.6, 0.04], head + np.array([0.0, 0.0, 0.18]), M.METAL),  # handlebar
        _bar(head, head + np.array([0.0, 0.0, 0.18]), 0.035),
    ]
    return M.concatenate(parts)


def fence(rng: np.random.Generator) -> M.Mesh:
    """Posts every 2-2.5 m joined by two or three thin rails, 4-12 m long."""
    length = float(rng.uniform(4.0, 12.0))
    height = float(rng.uniform(1.0, 1.8))
    posts = max(2, int(np.ceil(length / float(rng.uniform(2.0, 2.5)))) + 1)
    xs = np.linspace(-length / 2, length / 2, posts)
    parts = [M.box([0.08, 0.08, height], [x, 0.0, height / 2], M.METAL) for x in xs]
    for z in np.linspace(0.25, height - 0.05, int(rng.integers(2, 4))):
        parts.append(M.box([length, 0.04, 0.06], [0.0, 0.0, z], M.METAL))
    return M.concatenate(parts)


BUILDERS = {"bollard": bollard, "sign": sign, "bicycle": bicycle, "fence": fence}
