"""Street scenes: a road with parked and moving vehicles, pedestrians, clutter and an ego car.

World frame: x along the street (the ego drives toward +x), y left, z up, ground at
z = 0. One :class:`Street` holds every object of a sequence with a constant-velocity
motion (zero for parked cars and clutter); :meth:`Street.world_at` assembles the
triangle soup of one frame (one ray-casting geometry, per-triangle owner) and
:meth:`Street.boxes_at` the boxes of all labelled objects. Clutter is chosen to fool
detectors: low walls, bushes, vegetation blobs and bins have car-like extents; street furniture
(:mod:`pcc_ros.data.synthetic.furniture`: bollard rows, signs, bicycles, fences) and pedestrians
complete the non-vehicle world the detector's confusions sit on.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from pcc_ros.data.synthetic import mesh as M
from pcc_ros.data.synthetic.furniture import BUILDERS as FURNITURE_BUILDERS
from pcc_ros.data.synthetic.lidar import Layer
from pcc_ros.data.synthetic.vehicles import VehicleModel, random_vehicle
from pcc_ros.geometry.rotations import rotation_z

KIND_GROUND, KIND_STRUCTURE, KIND_VEHICLE, KIND_PEDESTRIAN, KIND_CLUTTER = range(5)


@dataclass(frozen=True)
class SceneParams:
    """Street layout parameters (metres, metres per second, seconds)."""

    frame_dt: float = 0.1
    lane_width: float = 3.4
    ego_speed: tuple[float, float] = (3.0, 11.0)
    parked_gap: tuple[float, float] = (0.6, 7.0)
    parked_empty: float = 0.25  # probability that a parking slot stays empty (a longer gap)
    perpendicular_parking: float = 0.25  # probability that a side parks perpendicular
    oncoming_spacing: tuple[float, float] = (14.0, 45.0)
    pedestrians_per_100m: float = 5.0
    poles_spacing: tuple[float, float] = (12.0, 30.0)
    clutter_per_100m: float = 9.0
    furniture_per_100m: float = 6.0  # bollard rows, signs, bicycle racks, fences (furniture.py), per side
    margin: float = 90.0  # street extends this far behind the first / beyond the last ego pose
    cull_range: float = 125.0
    #: vehicle families and weights, ``(("van", 1.0), ("suv", 1.0))`` (vehicles.family_weights); empty: street mix
    vehicle_mix: tuple = ()

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class SceneObject:
    """One object: a mesh in its own frame (centred on its box) and a constant-velocity pose."""

    kind: int
    name: str  # "sedan", "pole", "bush", ... (family for vehicles)
    mesh: M.Mesh
    size: np.ndarray  # (3,) box length, width, height
    position: np.ndarray  # (3,) box centre at t = 0, world
    yaw: float
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(2))
    label: str = ""  # KITTI class for labelled objects ("Car", "Van", "Pedestrian")
    track_id: int = -1
    confusion: float = 0.0  # per-frame probability a car detector fires on this (clutter)
    model: VehicleModel | None = None

    @property
    def moving(self) -> bool:
        return bool(np.any(self.velocity != 0))


@dataclass
class Street:
    """All objects of one sequence plus the ego trajectory."""

    objects: list[SceneObject]
    ego_xy: np.ndarray  # (F, 2)
    ego_yaw: np.ndarray  # (F,)
    params: SceneParams
    _static: tuple[M.Mesh, np.ndarray] | None = None
    _static_layer: Layer | None = None

    @property
    def frames(self) -> int:
        return len(self.ego_yaw)

    def centers_at(self, frame: int) -> np.ndarray:
        """``(K, 3)`` box centres of all objects at a frame."""
        t = frame * self.params.frame_dt
        pos = np.array([o.position for o in self.objects])
        vel = np.array([o.velocity for o in self.objects])
        pos[:, :2] += vel * t
        return pos

    def _static_world(self) -> tuple[M.Mesh, np.ndarray]:
        if self._static is None:
            parts, owner = [], []
            for i, o in enumerate(self.objects):
                if not o.moving:
                    parts.append(o.mesh.transformed(rotation_z(o.yaw), o.position))
                    owner.append(np.full(len(o.mesh.triangles), i, np.int32))
            self._static = (M.concatenate(parts), np.concatenate(owner))
        return self._static

    def static_layer(self) -> Layer:
        """Everything that does not move, as one ray-casting layer built once per sequence."""
        if self._static_layer is None:
            self._static_layer = Layer(*self._static_world())
        return self._static_layer

    def dynamic_layer(self, frame: int, near: np.ndarray | None = None) -> Layer:
        """The moving objects (within ``cull_range`` of ``near``) at a frame."""
        centers = self.centers_at(frame)
        parts, owners = [], []
        for i, o in enumerate(self.objects):  # moving objects only: a few dozen per sequence
            if o.moving and (near is None or np.hypot(*(centers[i, :2] - near)) < self.params.cull_range):
                parts.append(o.mesh.transformed(rotation_z(o.yaw), centers[i]))
                owners.append(np.full(len(o.mesh.triangles), i, np.int32))
        if not parts:
            return Layer(M.concatenate([]), np.zeros(0, np.int32))
        return Layer(M.concatenate(parts), np.concatenate(owners))

    def layers_at(self, frame: int, near: np.ndarray | None = None) -> list[Layer]:
        """Ray-casting layers of a frame: the cached static street and the moving objects."""
        return [self.static_layer(), self.dynamic_layer(frame, near)]

    def world_at(self, frame: int, near: np.ndarray | None = None) -> tuple[M.Mesh, np.ndarray]:
        """The frame's triangle soup in world coordinates and the owning object per triangle.

        ``near`` (2,) culls objects whose centre is beyond ``cull_range`` of that point
        (the ground and buildings are always kept).
        """
        static, static_owner = self._static_world()
        centers = self.centers_at(frame)
        keep_obj = np.ones(len(self.objects), dtype=bool)
        if near is not None:
            dist = np.linalg.norm(centers[:, :2] - near, axis=1)
            big = np.array([o.kind in (KIND_GROUND, KIND_STRUCTURE) for o in self.objects])
            keep_obj = big | (dist < self.params.cull_range)
        tri_keep = keep_obj[static_owner]
        parts = [M.Mesh(static.vertices, static.triangles[tri_keep], static.material[tri_keep],
                        static.component[tri_keep])]
        owners = [static_owner[tri_keep]]
        for i, o in enumerate(self.objects):  # moving objects only: a few dozen per sequence
            if o.moving and keep_obj[i]:
                parts.append(o.mesh.transformed(rotation_z(o.yaw), centers[i]))
                owners.append(np.full(len(o.mesh.triangles), i, np.int32))
        return M.concatenate(parts), np.concatenate(owners)

    def labelled(self) -> np.ndarray:
        """Indices of objects that get KITTI labels (vehicles and pedestrians)."""
        return np.array([i for i, o in enumerate(self.objects) if o.label], dtype=np.int64)

    def boxes_at(self, frame: int, index: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World centres ``(K, 3)``, sizes ``(K, 3)`` and yaws ``(K,)`` of the objects ``index``."""
        centers = self.centers_at(frame)[index]
        sizes = np.array([self.objects[i].size for i in index]).reshape(-1, 3)
        yaws = np.array([self.objects[i].yaw for i in index], dtype=np.float64)
        return centers, sizes, yaws


def _pedestrian(rng: np.random.Generator) -> M.Mesh:
    """Legs, torso, arms and head as closed primitives (about 1.55-1.95 m tall)."""
    h = float(rng.uniform(1.55, 1.95))
    leg = 0.47 * h
    stride = float(rng.uniform(-0.15, 0.15))
    parts = [
        M.cylinder(0.075, leg, 8, M.CLOTHING).transformed(np.eye(3), [stride, 0.1, 0.0]),
        M.cylinder(0.075, leg, 8, M.CLOTHING).transformed(np.eye(3), [-stride, -0.1, 0.0]),
        M.sphere(np.array([0.14, 0.22, 0.30 * h / 2 + 0.02]), [0, 0, leg + 0.15 * h], 1, M.CLOTHING),
        M.cylinder(0.05, 0.33 * h, 8, M.CLOTHING).transformed(np.eye(3), [-stride * 0.5, 0.27, leg - 0.02]),
        M.cylinder(0.05, 0.33 * h, 8, M.CLOTHING).transformed(np.eye(3), [stride * 0.5, -0.27, leg - 0.02]),
        M.sphere(0.11, [0, 0, h - 0.11], 1, M.CLOTHING),
    ]
    return M.concatenate(parts)


def _tiles(x0: float, x1: float, y0: float, y1: float, height: float, material: int, tile: float = 40.0) -> M.Mesh:
    """A slab ``[x0, x1] x [y0, y1] x [0, height]`` as adjacent closed boxes of at most ``tile`` metres."""
    nx, ny = max(1, int(np.ceil((x1 - x0) / tile))), max(1, int(np.ceil((y1 - y0) / tile)))
    xs, ys = np.linspace(x0, x1, nx + 1), np.linspace(y0, y1, ny + 1)
    return M.concatenate([
        M.box([xs[i + 1] - xs[i], ys[j + 1] - ys[j], height],
              [(xs[i] + xs[i + 1]) / 2, (ys[j] + ys[j + 1]) / 2, height / 2], material)
        for i in range(nx) for j in range(ny)
    ])


def _centred(mesh: M.Mesh) -> tuple[M.Mesh, np.ndarray, np.ndarray]:
    """Mesh shifted to its box centre; returns (mesh, size, offset applied)."""
    lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
    c = (lo + hi) / 2
    return M.Mesh(mesh.vertices - c, mesh.triangles, mesh.material, mesh.component), hi - lo, c


def _place(kind: int, name: str, mesh: M.Mesh, x: float, y: float, base_z: float, yaw: float, **kw) -> SceneObject:
    """A mesh built standing on z = 0 in its own frame, placed with its base at ``base_z``."""
    m, size, c = _centred(mesh)
    pos = np.array([x, y, 0.0]) + rotation_z(yaw) @ np.array([c[0], c[1], 0.0])
    pos[2] = base_z + c[2]
    return SceneObject(kind, name, m, size, pos, yaw, **kw)


def _vehicle(rng: np.random.Generator, x: float, y: float, yaw: float, track: int, velocity=(0.0, 0.0),
             mix: tuple = ()) -> SceneObject:
    model = random_vehicle(rng, mix=mix)
    return SceneObject(
        KIND_VEHICLE, model.family, model.mesh, model.size, np.array([x, y, model.size[2] / 2]), yaw,
        np.asarray(velocity, dtype=np.float64), model.label, track, 0.0, model,
    )


def _add_furniture(objects: list[SceneObject], rng: np.random.Generator, mean: float, x_lo: float, x_hi: float,
                  side: float, kerb: float, walk: float) -> None:
    """Street furniture on one side (a Poisson number of groups): rows of 3-8 bollards at the
    kerb, single signs at the kerb, racks of 1-4 bicycles on the sidewalk, fences at its back."""
    for _ in range(rng.poisson(mean)):
        name = str(rng.choice(["bollard", "sign", "bicycle", "fence"], p=[0.3, 0.25, 0.25, 0.2]))
        x = float(rng.uniform(x_lo, x_hi))
        if name == "bollard":
            step = float(rng.uniform(1.2, 1.8))
            for k in range(int(rng.integers(3, 9))):
                objects.append(_place(KIND_CLUTTER, name, FURNITURE_BUILDERS[name](rng), x + k * step,
                                      side * (kerb + 0.3), 0.14, 0.0, confusion=0.02))
        elif name == "sign":
            objects.append(_place(KIND_CLUTTER, name, FURNITURE_BUILDERS[name](rng), x, side * (kerb + 0.35), 0.14,
                                  float(rng.uniform(-np.pi, np.pi)), confusion=0.03))
        elif name == "bicycle":
            across = bool(rng.random() < 0.5)  # parked across the sidewalk side by side, or along it
            yaw = (np.pi / 2 if across else 0.0) + float(rng.normal(0, 0.1))
            step = 0.8 if across else 2.0
            for k in range(int(rng.integers(1, 5))):
                objects.append(_place(KIND_CLUTTER, name, FURNITURE_BUILDERS[name](rng), x + step * k,
                                      side * (kerb + float(rng.uniform(0.8, max(walk - 0.8, 0.9)))), 0.14, yaw,
                                      confusion=float(rng.beta(2, 6))))
        else:
            objects.append(_place(KIND_CLUTTER, name, FURNITURE_BUILDERS[name](rng), x,
                                  side * (kerb + walk - 0.1), 0.14, float(rng.normal(0, 0.02)),
                                  confusion=float(rng.beta(1.5, 6))))


def build_street(frames: int, params: SceneParams, rng: np.random.Generator) -> Street:
    """A random street and ego trajectory for ``frames`` frames (deterministic for ``rng``)."""
    p = params
    lanes = int(rng.choice([1, 2], p=[0.6, 0.4]))  # lanes per direction
    lw = p.lane_width
    road = lanes * lw  # half width of the carriageway
    dt = p.frame_dt
    duration = frames * dt
    v_ego = float(rng.uniform(*p.ego_speed)) if rng.random() > 0.1 else float(rng.uniform(0.0, 1.0))
    ego_lane_y = -lw / 2 - (lanes - 1) * lw * float(rng.integers(0, 2))
    ts = np.arange(frames) * dt
    wiggle_a, wiggle_w = float(rng.uniform(0.0, 0.25)), float(rng.uniform(0.1, 0.4))
    ego_x = v_ego * ts
    ego_y = ego_lane_y + wiggle_a * np.sin(wiggle_w * ts)
    dydx = wiggle_a * wiggle_w * np.cos(wiggle_w * ts) / max(v_ego, 0.5)
    ego_yaw = np.arctan(dydx) * min(v_ego, 1.0)
    x_lo, x_hi = -p.margin, float(ego_x[-1]) + p.margin
    length = x_hi - x_lo

    objects: list[SceneObject] = []
    track = 0
    # Ground: a slab (top at z = 0) in tiles, so no triangle is a long sliver (float32 accuracy).
    reach = p.cull_range + 10.0
    objects.append(_place(KIND_GROUND, "ground", _tiles(x_lo - reach, x_hi + reach, -reach, reach, 1.0, M.ASPHALT),
                          (x_lo + x_hi) / 2, 0.0, -1.0, 0.0))

    for side in (-1.0, 1.0):
        perpendicular = rng.random() < p.perpendicular_parking
        depth = 5.4 if perpendicular else 2.3
        kerb = road + depth
        walk = float(rng.uniform(2.5, 4.5))
        objects.append(_place(KIND_STRUCTURE, "sidewalk", _tiles(x_lo, x_hi, 0.0, walk, 0.14, M.CONCRETE, 10.0),
                              (x_lo + x_hi) / 2, side * (kerb + walk / 2), 0.0, 0.0))
        # Parked vehicles.
        x = x_lo + float(rng.uniform(0, 5))
        while x < x_hi:
            if rng.random() < p.parked_empty:
                x += float(rng.uniform(3.0, 12.0))
                continue
            yaw_base = (np.pi / 2 if rng.random() < 0.5 else -np.pi / 2) if perpendicular else (
                0.0 if side < 0 or rng.random() < 0.5 else np.pi)
            yaw = yaw_base + float(rng.normal(0, 0.04 if not perpendicular else 0.08))
            obj = _vehicle(rng, 0.0, 0.0, yaw, track, mix=p.vehicle_mix)
            extent = obj.size[1] if perpendicular else obj.size[0]
            x += extent / 2
            inset = obj.size[0] / 2 + 0.3 if perpendicular else obj.size[1] / 2 + 0.25
            obj.position[:2] = [x, side * (kerb - inset + float(rng.normal(0, 0.08)))]
            objects.append(obj)
            track += 1
            x += extent / 2 + float(rng.uniform(*p.parked_gap)) * (0.4 if perpendicular else 1.0)
        # Buildings with gaps, set back behind the sidewalk.
        x = x_lo
        while x < x_hi:
            seg = float(rng.uniform(8, 40))
            if rng.random() < 0.8:
                setback = float(rng.uniform(0.0, 4.0))
                hgt = float(rng.uniform(3.0, 14.0))
                yb = side * (kerb + walk + setback + 5.0)
                objects.append(_place(KIND_STRUCTURE, "building", M.box([seg, 10.0, hgt], [0, 0, hgt / 2]),
                                      x + seg / 2, yb, 0.0, 0.0))
            x += seg + float(rng.uniform(0, 10))
        # Poles (street lights, signs) at the kerb.
        x = x_lo + float(rng.uniform(0, 10))
        while x < x_hi:
            hgt = float(rng.uniform(2.5, 8.0))
            r = float(rng.uniform(0.05, 0.15))
            objects.append(_place(KIND_CLUTTER, "pole", M.cylinder(r, hgt, 10, M.METAL),
                                  x, side * (kerb + 0.4), 0.14, 0.0, confusion=0.01))
            x += float(rng.uniform(*p.poles_spacing))
        # Detector-fooling clutter on the sidewalk edge / in front of buildings.
        n_clutter = rng.poisson(p.clutter_per_100m * length / 100.0)
        for _ in range(n_clutter):
            cx = float(rng.uniform(x_lo, x_hi))
            cy = side * (kerb + float(rng.uniform(0.3, walk + 2.0)))
            kind = rng.choice(["bush", "blob", "low_wall", "bin", "tree"], p=[0.28, 0.2, 0.2, 0.14, 0.18])
            yaw = float(rng.uniform(-np.pi, np.pi))
            if kind == "bush":
                rad = rng.uniform([0.6, 0.5, 0.4], [2.0, 1.0, 0.9])
                mesh = M.sphere(rad, [0, 0, rad[2] * 0.9], 2, M.VEGETATION, rng, 0.25)
                conf = float(rng.beta(2, 5))
            elif kind == "blob":
                rad = rng.uniform([1.2, 0.6, 0.5], [2.5, 1.1, 0.9])
                mesh = M.sphere(rad, [0, 0, rad[2] * 0.8], 2, M.VEGETATION, rng, 0.35)
                conf = float(rng.beta(2, 4))
            elif kind == "low_wall":
                size = rng.uniform([3.0, 0.25, 0.9], [8.0, 0.5, 1.6])
                mesh = M.box(size, [0, 0, size[2] / 2], M.CONCRETE)
                yaw = float(rng.normal(0, 0.05))
                cy = side * (kerb + walk + float(rng.uniform(0.5, 3.0)))
                conf = float(rng.beta(1.5, 5))
            elif kind == "bin":
                size = rng.uniform([1.2, 0.8, 1.0], [2.2, 1.4, 1.5])
                mesh = M.box(size, [0, 0, size[2] / 2], M.METAL)
                conf = float(rng.beta(2, 3))
            else:
                trunk_h = float(rng.uniform(1.5, 3.0))
                crown = rng.uniform([1.2, 1.2, 1.2], [3.0, 3.0, 2.5])
                mesh = M.concatenate([M.cylinder(float(rng.uniform(0.1, 0.25)), trunk_h + 0.5, 10, M.VEGETATION),
                                      M.sphere(crown, [0, 0, trunk_h + crown[2] * 0.9], 2, M.VEGETATION, rng, 0.3)])
                conf = float(rng.beta(1, 8))
            objects.append(_place(KIND_CLUTTER, str(kind), mesh, cx, cy, 0.14, yaw, confusion=conf))
        _add_furniture(objects, rng, p.furniture_per_100m * length / 100.0, x_lo, x_hi, side, kerb, walk)
        # Pedestrians on the sidewalk, walking along it or standing.
        for _ in range(rng.poisson(p.pedestrians_per_100m * length / 100.0)):
            speed = float(rng.choice([-1, 1])) * float(rng.uniform(0.8, 1.6)) if rng.random() < 0.7 else 0.0
            yaw = 0.0 if speed >= 0 else np.pi
            yaw = yaw if speed != 0 else float(rng.uniform(-np.pi, np.pi))
            ped = _place(KIND_PEDESTRIAN, "pedestrian", _pedestrian(rng), float(rng.uniform(x_lo, x_hi)),
                         side * (kerb + float(rng.uniform(0.5, walk - 0.5))), 0.14, yaw,
                         velocity=np.array([speed, 0.0]), label="Pedestrian", track_id=track, confusion=0.03)
            objects.append(ped)
            track += 1

    # Moving traffic: per lane a common speed (no overtaking inside a lane, so no collisions).
    for lane in range(lanes):
        for direction in (1.0, -1.0):
            y = -direction * (lw / 2 + lane * lw)  # drive on the right: +x traffic at negative y
            ego_lane = direction > 0 and abs(y - ego_lane_y) < 1e-6
            if ego_lane:  # a queue ahead of the ego at its speed
                speed, x, x_end = v_ego, float(ego_x[0]) + float(rng.uniform(8, 25)), float(ego_x[0]) + 120.0
            elif direction > 0:
                speed = float(rng.uniform(4.0, 14.0))
                x, x_end = x_lo - speed * duration, x_hi
            else:
                speed = -float(rng.uniform(5.0, 14.0))
                x, x_end = x_lo, x_hi - speed * duration
            if speed < 0.5 and speed >= 0:
                speed = 0.0
            while x < x_end:
                obj = _vehicle(rng, 0.0, 0.0, 0.0 if direction > 0 else np.pi, track, velocity=(speed, 0.0),
                               mix=p.vehicle_mix)
                obj.position[:2] = [x, y + float(rng.normal(0, 0.1))]
                objects.append(obj)
                track += 1
                x += obj.size[0] + float(rng.uniform(*p.oncoming_spacing))
    return Street(objects, np.stack([ego_x, ego_y], 1), ego_yaw, params)
