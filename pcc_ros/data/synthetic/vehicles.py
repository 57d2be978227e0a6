"""Procedural vehicle meshes: seven families with shaped bodies, wheels and wheel arches.

A body is lofted along its length: a side profile (roof line over the bumper, trunk
deck, rear window, roof, windshield, hood) gives the top of each cross-section, the
ground clearance with arch cut-outs over the wheels gives its bottom, and the section
between them is a superellipse whose half-width narrows above the belt line (the
greenhouse tumblehome) and at the rounded bumper corners. Wheels are closed cylinders
standing on the ground inside the arches; a pickup adds bed rails and a tailgate over
a lowered bed floor. Each part is a closed component (see :mod:`.mesh`).

Sizes follow KITTI: the families labelled ``Car`` (sedan, hatchback, wagon = estate, SUV) are
mixed so their mean box is about 3.9 x 1.6 x 1.5 m (KITTI's car mean is 3.88 x 1.63 x
1.53 m); vans and pickups are larger and labelled ``Van``, as KITTI's annotators did
for vans, minibuses and most pickups / large utility vehicles. Small box trucks (a cab in
front of a taller cargo box, ``Truck``) are not in the default street mix; a scene asks for
them, or for any other mix, with ``SceneParams.vehicle_mix`` (``pcc synth --vehicle-mix``).
The per-family sizes and the production vehicles they are modelled on: ``docs/synthcars.md``.

The mesh is centred on its tight axis-aligned box, x to the front, z up, so the box
*is* the ground-truth label and the canonical frame is a plain scaling.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from pcc_ros.data.synthetic.mesh import GLASS, PAINT, TYRE, Mesh, box, concatenate, cylinder, sample_surface, tube

FAMILIES = ("sedan", "hatchback", "wagon", "suv", "van", "pickup", "truck")
LABELS = {"sedan": "Car", "hatchback": "Car", "wagon": "Car", "suv": "Car", "van": "Van", "pickup": "Van",
          "truck": "Truck"}
#: Other names of a family (British usage: an estate car is a station wagon).
ALIASES = {"estate": "wagon", "station_wagon": "wagon", "minivan": "van", "box_truck": "truck"}
# Street mix: car families dominate as on KITTI's streets.
FAMILY_WEIGHTS = {"sedan": 0.28, "hatchback": 0.34, "wagon": 0.14, "suv": 0.12, "van": 0.08, "pickup": 0.04}

# family -> (mean, std) of length, width, height in metres.
_SIZE = {
    "sedan": ((4.15, 0.22), (1.68, 0.05), (1.44, 0.04)),
    "hatchback": ((3.70, 0.22), (1.62, 0.05), (1.47, 0.05)),
    "wagon": ((4.20, 0.22), (1.68, 0.05), (1.50, 0.04)),
    "suv": ((4.25, 0.25), (1.78, 0.06), (1.68, 0.06)),
    "van": ((4.90, 0.30), (1.90, 0.06), (1.98, 0.12)),
    "pickup": ((5.10, 0.30), (1.88, 0.06), (1.80, 0.07)),
    "truck": ((6.20, 0.45), (2.05, 0.06), (2.85, 0.15)),
}

_STATIONS = 44
_RING = 20


@dataclass
class VehicleModel:
    """One vehicle: mesh centred on its box, box size, label and generating parameters."""

    family: str
    label: str
    mesh: Mesh
    size: np.ndarray  # (3,) length, width, height
    params: dict = field(default_factory=dict)


def family_weights(mix: object = None) -> dict[str, float]:
    """A vehicle mix as ``{family: weight}``: ``None`` / empty is the street mix
    (:data:`FAMILY_WEIGHTS`); otherwise a mapping or ``(family, weight)`` pairs (the form a
    ``SceneParams`` stores), aliases (``estate``) resolved. Unknown families, negative weights
    or an all-zero mix raise ``ValueError`` naming them."""
    if not mix:
        return dict(FAMILY_WEIGHTS)
    pairs = mix.items() if isinstance(mix, dict) else mix
    out: dict[str, float] = {}
    for name, weight in pairs:  # a handful of families
        family = ALIASES.get(str(name), str(name))
        if family not in FAMILIES:
            raise ValueError(f"unknown vehicle family {name!r} (known: {', '.join(FAMILIES)}; "
                             f"aliases: {', '.join(ALIASES)})")
        if not float(weight) >= 0:
            raise ValueError(f"vehicle family {name!r}: weight must be >= 0, got {weight}")
        out[family] = out.get(family, 0.0) + float(weight)
    if sum(out.values()) <= 0:
        raise ValueError(f"vehicle mix {dict(out)} has no positive weight")
    return out


def sample_family(rng: np.random.Generator, mix: object = None) -> str:
    """A family drawn from ``mix`` (:func:`family_weights`; default the street mix)."""
    weights = family_weights(mix)
    names = list(weights)
    p = np.array([weights[n] for n in names])
    return names[int(rng.choice(len(names), p=p / p.sum()))]


def _profile(family: str, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """Top profile key points ``(u, h)``: u in [0, 1] rear -> front, h = z / height.

    Also returns the greenhouse landmarks used for glass and tumblehome.
    """
    j = lambda a, b: float(rng.uniform(a, b))  # noqa: E731 - short jitter helper
    if family == "sedan":
        deck, hood = j(0.64, 0.72), j(0.60, 0.67)
        trunk, rw, roof_end, ws = j(0.17, 0.23), j(0.33, 0.38), j(0.58, 0.63), j(0.70, 0.75)
        pts = [(0, deck - 0.16), (0.025, deck - 0.02), (trunk, deck), (rw, 0.98), (rw + 0.04, 1.0),
               (roof_end, 1.0), (ws, hood + 0.05), (0.965, hood), (1.0, hood - 0.17)]
        glass = (trunk + 0.01, ws)
    elif family == "hatchback":
        hood = j(0.60, 0.67)
        tail, roof_start, roof_end, ws = j(0.72, 0.80), j(0.10, 0.16), j(0.56, 0.62), j(0.70, 0.76)
        pts = [(0, 0.48), (0.02, tail), (0.06, 0.90), (roof_start, 1.0), (roof_end, 1.0),
               (ws, hood + 0.05), (0.96, hood), (1.0, hood - 0.17)]
        glass = (0.03, ws)
    elif family in ("wagon", "suv"):
        hood = j(0.62, 0.68) if family == "wagon" else j(0.66, 0.74)
        roof_end, ws = j(0.58, 0.64), j(0.70, 0.76)
        pts = [(0, 0.50), (0.015, 0.74), (0.035, 0.95), (0.07, 1.0), (roof_end, 1.0),
               (ws, hood + 0.05), (0.965, hood), (1.0, hood - 0.16)]
        glass = (0.02, ws)
    elif family == "van":
        hood = j(0.50, 0.58)
        roof_end, ws = j(0.76, 0.82), j(0.86, 0.90)
        pts = [(0, 0.40), (0.012, 0.93), (0.03, 1.0), (roof_end, 1.0), (ws, hood + 0.08),
               (0.975, hood), (1.0, hood - 0.14)]
        glass = (roof_end - 0.18, ws)
    elif family == "truck":  # a tall cargo box behind a lower cab with a near-vertical windscreen
        cab, box_end = j(0.70, 0.78), j(0.70, 0.75)
        pts = [(0, 0.30), (0.006, 0.97), (0.015, 1.0), (box_end, 1.0), (box_end + 0.012, cab),
               (0.90, cab), (0.975, 0.62 * cab), (1.0, 0.45 * cab)]
        glass = (box_end + 0.04, 0.975)
    elif family == "pickup":
        floor, hood = j(0.50, 0.56), j(0.62, 0.68)
        bed, roof_end, ws = j(0.36, 0.42), j(0.60, 0.64), j(0.72, 0.76)
        pts = [(0, floor - 0.08), (0.015, floor), (bed, floor), (bed + 0.01, 0.97), (bed + 0.03, 1.0),
               (roof_end, 1.0), (ws, hood + 0.05), (0.965, hood), (1.0, hood - 0.15)]
        glass = (bed + 0.01, ws)
    else:
        raise ValueError(f"unknown vehicle family {family!r}")
    return np.array(pts, dtype=np.float64), {"glass_u": glass, "hood": pts[-2][1]}


def build_vehicle(family: str, rng: np.random.Generator) -> VehicleModel:
    """A random vehicle of ``family`` (deterministic for the generator's state)."""
    (lm, ls), (wm, ws), (hm, hs) = _SIZE[family]
    length = float(np.clip(rng.normal(lm, ls), lm - 2.5 * ls, lm + 2.5 * ls))
    width = float(np.clip(rng.normal(wm, ws), wm - 2.5 * ws, wm + 2.5 * ws))
    height = float(np.clip(rng.normal(hm, hs), hm - 2.5 * hs, hm + 2.5 * hs))
    big = family in ("suv", "van", "pickup", "truck")
    wheel_r = float(rng.uniform(0.33, 0.39) if big else rng.uniform(0.28, 0.32))
    wheel_w = float(rng.uniform(0.20, 0.26) if big else rng.uniform(0.17, 0.22))
    clearance = float(rng.uniform(0.20, 0.26) if big else rng.uniform(0.13, 0.18))
    short_nose = family in ("van", "truck")
    front_oh = float(rng.uniform(0.12, 0.16) * length) if short_nose else float(rng.uniform(0.17, 0.22) * length)
    rear_oh = float(rng.uniform(0.15, 0.22) * length)
    tumble = float(rng.uniform(0.10, 0.20))
    if family == "truck":  # a cargo box has straight walls
        tumble *= 0.2
    squareness = float(rng.uniform(4.0, 7.0))
    key, marks = _profile(family, rng)
    belt = marks["hood"] + float(rng.uniform(0.02, 0.06))

    # Stations clustered at the ends (bumper rounding) with enough in the middle for the arches.
    s = np.linspace(0.0, 1.0, _STATIONS)
    u = 0.5 - 0.5 * np.cos(np.pi * s)
    u = np.sort(np.unique(np.r_[u, np.linspace(0, 1, 28)]))
    x = (u - 0.5) * length
    top = np.interp(u, key[:, 0], key[:, 1]) * height
    for _ in range(2):  # soften profile kinks into curves
        top[1:-1] = 0.25 * top[:-2] + 0.5 * top[1:-1] + 0.25 * top[2:]
    top *= height / top.max()
    # Bottom: clearance, rising under the overhanging bumpers, cut by the wheel arches.
    end = np.clip(np.minimum(u, 1 - u) / 0.07, 0.0, 1.0)
    bottom = clearance + (1 - end) ** 2 * 0.12
    axles = np.array([-length / 2 + rear_oh, length / 2 - front_oh])
    arch_r = wheel_r + float(rng.uniform(0.03, 0.06))
    for ax in axles:
        dx = x - ax
        inside = np.abs(dx) < arch_r
        bottom[inside] = np.maximum(bottom[inside], wheel_r + np.sqrt(arch_r**2 - dx[inside] ** 2))
    bottom = np.minimum(bottom, top - 0.12)

    # Cross-sections: superellipse between bottom and top; narrower above the belt and at the corners.
    t = np.linspace(0, 2 * np.pi, _RING, endpoint=False)
    cy, sz = np.cos(t), np.sin(t)
    ey = np.sign(cy) * np.abs(cy) ** (2 / squareness)
    ez = np.sign(sz) * np.abs(sz) ** (2 / squareness)
    zc, hz = (top + bottom) / 2, (top - bottom) / 2
    z = zc[:, None] + hz[:, None] * ez[None, :]
    belt_z = belt * height
    green = np.clip((z - belt_z) / max(height - belt_z, 1e-3), 0, 1)
    half_w = width / 2 * (1 - tumble * green**1.3)
    d = np.minimum(u, 1 - u)
    plan = 1 - 0.10 * np.clip(1 - d / 0.08, 0, 1) ** 2  # rounded corners in plan view
    y = half_w * plan[:, None] * ey[None, :]
    # Bumper faces: the last few centimetres curl in toward the section centre.
    curl = np.where(d < 0.025, 0.6 + 0.4 * np.sqrt(np.clip(1 - (1 - d / 0.025) ** 2, 0, 1)), 1.0)
    y *= curl[:, None]
    z = zc[:, None] + (z - zc[:, None]) * curl[:, None]
    rings = np.stack([np.broadcast_to(x[:, None], y.shape), y, z], -1)

    # Glass: greenhouse quads above the belt, except the flat roof panel.
    zq = 0.5 * (z[:-1] + z[1:])
    zq = 0.5 * (zq + np.roll(zq, -1, axis=1))
    uq = 0.5 * (u[:-1] + u[1:])
    top_q = 0.5 * (top[:-1] + top[1:])
    g0, g1 = marks["glass_u"]
    glass = (zq > belt_z + 0.05) & (uq[:, None] > g0) & (uq[:, None] < g1)
    flat_roof = (top_q[:, None] > 0.97 * height) & (zq > top_q[:, None] - 0.06)
    material = np.where(glass & ~flat_roof, GLASS, PAINT).astype(np.int8)
    parts = [tube(rings, material)]

    yw = width / 2 - wheel_w / 2 - 0.02
    for ax in axles:
        for side in (-1.0, 1.0):
            wheel = cylinder(wheel_r, wheel_w, segments=18, material=TYRE)
            # Cylinder axis z -> y: rotate about x by -90 deg, then place.
            rot = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
            parts.append(wheel.transformed(rot, np.array([ax, side * yw - wheel_w / 2, wheel_r])))
    if family == "pickup":
        floor_z = float(np.interp(0.2, key[:, 0], key[:, 1]) * height)
        rail_z = float(rng.uniform(0.70, 0.76) * height)
        bed_x0, bed_x1 = -length / 2 + 0.03, (marks["glass_u"][0] - 0.5) * length
        rail_t = 0.07
        for side in (-1.0, 1.0):
            c = [(bed_x0 + bed_x1) / 2, side * (width / 2 - 0.03 - rail_t / 2), (floor_z - 0.05 + rail_z) / 2]
            parts.append(box([bed_x1 - bed_x0, rail_t, rail_z - floor_z + 0.05], c, PAINT))
        c = [bed_x0 + 0.04, 0.0, (floor_z - 0.05 + rail_z) / 2]
        parts.append(box([0.07, width - 0.08, rail_z - floor_z + 0.05], c, PAINT))
    mesh = concatenate(parts)
    lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
    mesh.vertices = mesh.vertices - (lo + hi) / 2
    params = {
        "family": family, "length": length, "width": width, "height": height, "wheel_radius": wheel_r,
        "wheel_width": wheel_w, "clearance": clearance, "front_overhang": front_oh, "rear_overhang": rear_oh,
        "tumblehome": tumble, "squareness": squareness, "belt": belt, "profile": key.round(4).tolist(),
    }
    return VehicleModel(family, LABELS[family], mesh, hi - lo, params)


def random_vehicle(rng: np.random.Generator, family: str | None = None, mix: object = None) -> VehicleModel:
    """A vehicle of the given family (an alias such as ``estate`` accepted), else of one drawn from
    ``mix`` (:func:`family_weights`; default the street mix, whose draws are unchanged)."""
    if family is not None:
        family = ALIASES.get(family, family)
    return build_vehicle(family or sample_family(rng, mix), rng)


def surface_samples(model: VehicleModel, n: int, rng: np.random.Generator) -> np.ndarray:
    """``(n, 3)`` points uniform by area on the *outer* surface, in the vehicle (box) frame.

    Samples of a component that lie inside another closed component (the top of a
    wheel inside the body, rail ends inside the bed) are not part of the visible
    surface and are dropped before drawing the final ``n``.
    """
    mesh = model.mesh
    keep_all: list[np.ndarray] = []
    have = 0
    scenes = []
    for c in range(mesh.n_components):
        v, t = mesh.component_mesh(c)
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(t.astype(np.uint32)))
        scenes.append(scene)
    while have < n:
        pts, tri = sample_surface(mesh, int(n * 1.3) + 64, rng)
        comp = mesh.component[tri]
        hidden = np.zeros(len(pts), dtype=bool)
        query = o3d.core.Tensor(pts.astype(np.float32))
        for c, scene in enumerate(scenes):
            occ = scene.compute_occupancy(query).numpy() > 0.5
            hidden |= occ & (comp != c)
        keep_all.append(pts[~hidden])
        have += int((~hidden).sum())
    return np.concatenate(keep_all)[:n]


def canonical_shape(model: VehicleModel, n: int, rng: np.random.Generator) -> np.ndarray:
    """``(n, 3)`` float32 complete surface in the canonical car frame (box centre, / length)."""
    return (surface_samples(model, n, rng) / model.size[0]).astype(np.float32)
