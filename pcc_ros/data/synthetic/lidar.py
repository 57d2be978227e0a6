"""A spinning LiDAR, simulated by one batched ray cast per frame.

The beam layout is a named sensor of :data:`pcc_ros.geometry.beams.SENSOR_PRESETS` (the table
the filter's beam model reads too), by default the Velodyne HDL-64E as on KITTI's car (upper
block +2.0 deg to -8.33 deg in 1/3 deg steps, lower block -8.83 deg to -24.9 deg in ~1/2 deg
steps, 2083 columns at ~0.17 deg, ~133k rays); ``vlp16``, ``os1_64``, ``pandar64``, two stacked
``vlp32c`` ... are one ``layout=`` away. Every ray of a
frame goes to open3d's ``RaycastingScene.cast_rays`` in a single call against the whole
world (ground, vehicles, clutter), so occlusion, self-occlusion and ground returns are
physical. Returns then get Gaussian range noise, random dropout (more on glass and on
weak far returns) and an intensity from the material albedo and the incidence angle.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from functools import cached_property

import numpy as np
import open3d as o3d

from pcc_ros.data.synthetic.mesh import MATERIALS, Mesh
from pcc_ros.geometry.beams import SensorModel, linspace_blocks, sensor_preset

_ALBEDO = np.array([MATERIALS[k][1] for k in sorted(MATERIALS)])
_MAT_DROP = np.array([MATERIALS[k][2] for k in sorted(MATERIALS)])


#: What :meth:`Sensor.realistic` adds to the ideal sensor.
REALISTIC_ARTEFACTS = {"beam_range_bias": 0.015, "beam_elevation_error": 0.04, "mixed_pixel_prob": 0.5,
                       "range_noise_per_100m": 0.04, "weak_dropout": 0.3}


@dataclass(frozen=True)
class Sensor:
    """Sensor model parameters (angles in degrees, distances in metres)."""

    #: the beam layout: a name of pcc_ros.geometry.beams.SENSOR_PRESETS, or any name when both
    #: ``elevation_table`` and ``azimuth_step`` are given (a sensor read from a user's scans)
    layout: str = "hdl64"
    #: an explicit elevation table (degrees, any order) instead of the layout's (``low_res``)
    elevation_table: tuple[float, ...] = ()
    #: degrees between two firings of a beam; 0: the layout's
    azimuth_step: float = 0.0
    mount_height: float = 1.73
    max_range: float = 120.0
    min_range: float = 2.5  # KITTI-style removal of near returns (ego vehicle)
    range_noise: float = 0.02
    dropout: float = 0.04
    far_dropout: float = 0.25  # extra dropout of weak returns at max range (grows with range^2)
    #: Per-laser calibration residuals (fixed per sensor seed): range offset (m, std) and
    #: elevation error (deg, std). They thicken a surface into per-ring layers as on a real HDL-64E.
    beam_range_bias: float = 0.0
    beam_elevation_error: float = 0.0
    #: Mixed pixels: a beam whose footprint straddles a depth edge (neighbouring column more than
    #: ``mixed_pixel_edge`` metres farther) returns, with this probability, a range between the
    #: two surfaces: the trailing points behind car silhouettes in real scans.
    mixed_pixel_prob: float = 0.0
    mixed_pixel_edge: float = 0.3
    calibration_seed: int = 0
    #: Range noise growing with range (std added per 100 m): real surfaces thicken with range.
    range_noise_per_100m: float = 0.0
    #: Extra dropout of weak returns (glass, dark or grazing surfaces) at every range.
    weak_dropout: float = 0.0

    def __post_init__(self) -> None:
        _ = self.model  # an unknown layout or a bad table fails here, naming it

    @classmethod
    def low_res(cls, **overrides) -> Sensor:
        """A 16-beam, 0.8 deg variant of the HDL-64E with the same field of view, for fast tests."""
        table = linspace_blocks((2.0, -8.33, 8), (-8.83, -24.9, 8))
        return cls(**{"elevation_table": table, "azimuth_step": 0.8, **overrides})

    @cached_property
    def model(self) -> SensorModel:
        """The nominal beam layout (the filter's :class:`~pcc_ros.geometry.beams.SensorModel`)."""
        if self.elevation_table and self.azimuth_step:
            return SensorModel(self.elevation_table, self.azimuth_step, self.layout)
        preset = sensor_preset(self.layout)
        if not self.elevation_table and not self.azimuth_step:
            return preset
        return SensorModel(self.elevation_table or preset.elevations_deg,
                           self.azimuth_step or preset.azimuth_resolution_deg, self.layout)

    @property
    def beams(self) -> int:
        return self.model.rings

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def realistic(cls, **overrides) -> Sensor:
        """The HDL-64E with the real-scan artefacts the domain-gap comparison showed missing
        (``python -m pcc_ros.data.domain_gap``): per-laser calibration residuals and mixed pixels."""
        return cls(**{**REALISTIC_ARTEFACTS, **overrides})

    @cached_property
    def elevations(self) -> np.ndarray:
        """``(beams,)`` elevation angles in degrees, top beam first (with the per-laser errors)."""
        nominal = self.model.top_first()
        if self.beam_elevation_error > 0:
            nominal = nominal + self._calibration[1] * self.beam_elevation_error
        return nominal

    @cached_property
    def _calibration(self) -> np.ndarray:
        """``(2, beams)`` standard-normal draws for the range and elevation residuals."""
        return np.random.default_rng([self.calibration_seed, 6464]).standard_normal((2, self.beams))

    @cached_property
    def beam_bias(self) -> np.ndarray:
        """``(beams,)`` range offset of each laser, metres."""
        return self._calibration[0] * self.beam_range_bias

    @cached_property
    def azimuths(self) -> np.ndarray:
        """``(columns,)`` azimuth angles in degrees, counter-clockwise from +x."""
        columns = round(self.model.columns)
        return np.arange(columns) * (360.0 / columns)

    @cached_property
    def directions(self) -> np.ndarray:
        """``(beams * columns, 3)`` unit ray directions in the sensor frame (beam-major)."""
        el = np.deg2rad(self.elevations)[:, None]
        az = np.deg2rad(self.azimuths)[None, :]
        d = np.stack(np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)), -1)
        return d.reshape(-1, 3)

    @property
    def n_rays(self) -> int:
        return len(self.elevations) * len(self.azimuths)


@dataclass
class Scan:
    """One simulated frame in the sensor frame.

    Attributes:
        points: ``(N, 4)`` float32 x, y, z, intensity (0..1), as KITTI stores them.
        owner: ``(N,)`` int32 object index (``Mesh``-level owner given to :func:`cast`) of each return.
        ray: ``(N,)`` int64 index of the ray each return came from.
        true_range: ``(N,)`` float64 noise-free range of each return.
    """

    points: np.ndarray
    owner: np.ndarray
    ray: np.ndarray
    true_range: np.ndarray


def build_scene(mesh: Mesh) -> o3d.t.geometry.RaycastingScene:
    """A ray-casting scene of one triangle soup (a single geometry; owners via primitive ids)."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.ascontiguousarray(mesh.vertices, dtype=np.float32)),
        o3d.core.Tensor(np.ascontiguousarray(mesh.triangles, dtype=np.uint32)),
    )
    return scene


class Layer:
    """A triangle soup, the owning object of each triangle, and its ray-casting scene.

    The world is cast as a few layers (the static street, built once per sequence, and
    the moving objects of the frame): building the BVH costs about twice as much as
    casting a revolution, so the static part must not be rebuilt every frame. The
    nearest hit over the layers is the first hit in the union.
    """

    def __init__(self, mesh: Mesh, owner: np.ndarray) -> None:
        self.mesh, self.owner = mesh, owner
        self._scene: o3d.t.geometry.RaycastingScene | None = None

    @property
    def scene(self) -> o3d.t.geometry.RaycastingScene:
        if self._scene is None:
            self._scene = build_scene(self.mesh)
        return self._scene


def cast(
    sensor: Sensor,
    world: Mesh | list[Layer],
    owner: np.ndarray | None,
    origin: np.ndarray,
    yaw: float,
    rng: np.random.Generator,
) -> Scan:
    """Cast every ray of one revolution from ``origin`` (world) with heading ``yaw``.

    ``world`` is the frame's whole scene in world coordinates with ``owner`` the object
    index of each triangle, or a list of :class:`Layer` (``owner`` then None). The returned
    points are in the sensor frame (x along the heading, z up), as a KITTI scan stores them.
    """
    layers = [Layer(world, owner)] if isinstance(world, Mesh) else [w for w in world if len(w.mesh.triangles)]
    c, s = np.cos(yaw), np.sin(yaw)
    local = sensor.directions
    world_dir = np.stack([c * local[:, 0] - s * local[:, 1], s * local[:, 0] + c * local[:, 1], local[:, 2]], 1)
    rays = np.empty((len(local), 6), dtype=np.float32)
    rays[:, :3] = origin
    rays[:, 3:] = world_dir
    rays_t = o3d.core.Tensor(rays)
    hits = [layer.scene.cast_rays(rays_t) for layer in layers]
    t_all = np.stack([h["t_hit"].numpy() for h in hits])
    which = np.argmin(t_all, axis=0) if len(hits) > 1 else np.zeros(len(rays), np.int64)
    t = np.take_along_axis(t_all, which[None], 0)[0].astype(np.float64)
    mixed_t = _mixed_pixels(sensor, t, rng) if sensor.mixed_pixel_prob > 0 else None
    ok = np.isfinite(t) & (t <= sensor.max_range) & (t >= sensor.min_range)
    ray = np.flatnonzero(ok)
    t, which = t[ok], which[ok]
    normal = np.empty((len(ray), 3))
    material = np.empty(len(ray), np.int8)
    obj = np.empty(len(ray), np.int32)
    for k, (layer, hit) in enumerate(zip(layers, hits)):  # a couple of layers
        sel = which == k
        prim = hit["primitive_ids"].numpy()[ray[sel]].astype(np.int64)
        normal[sel] = hit["primitive_normals"].numpy()[ray[sel]]
        material[sel] = layer.mesh.material[prim]
        obj[sel] = layer.owner[prim]
    cos_inc = np.abs(np.einsum("ij,ij->i", normal, world_dir[ray]))
    albedo = _ALBEDO[material]
    # Weak returns (dark, grazing, far) are lost more often, as on real scanners.
    strength = albedo * (0.25 + 0.75 * cos_inc)
    weak = 1.0 - np.clip(strength / 0.4, 0, 1)
    p_drop = sensor.dropout + _MAT_DROP[material] + sensor.far_dropout * (t / sensor.max_range) ** 2 * weak
    if sensor.weak_dropout > 0:
        p_drop = p_drop + sensor.weak_dropout * weak
    keep = rng.random(len(t)) >= p_drop
    noisy = t + rng.normal(0.0, sensor.range_noise, len(t)) if sensor.range_noise > 0 else t.copy()
    if sensor.range_noise_per_100m > 0:
        noisy += rng.normal(0.0, 1.0, len(t)) * (sensor.range_noise_per_100m * t / 100.0)
    if sensor.beam_range_bias > 0:
        noisy += sensor.beam_bias[ray // len(sensor.azimuths)]
    if mixed_t is not None:
        noisy += mixed_t[ray]
    intensity = np.clip(strength * np.exp(-t / 200.0) + rng.normal(0.0, 0.02, len(t)), 0.0, 0.99)
    ray, t, noisy, obj, intensity = ray[keep], t[keep], noisy[keep], obj[keep], intensity[keep]
    points = np.empty((len(ray), 4), dtype=np.float32)
    points[:, :3] = local[ray] * noisy[:, None]
    points[:, 3] = intensity
    return Scan(points, obj, ray, t)


def _mixed_pixels(sensor: Sensor, t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Range added to each ray (0 for most) by a footprint that straddles a depth edge.

    The range image is (beams, columns); a ray whose left or right neighbour hits something
    more than ``mixed_pixel_edge`` farther (or nothing) while the other neighbour is on its
    own surface returns, with ``mixed_pixel_prob``, a range uniformly between its own surface
    and the neighbour's (capped at 2 m behind it).
    """
    cols = len(sensor.azimuths)
    image = np.where(np.isfinite(t), t, np.inf).reshape(-1, cols)
    edge_m = sensor.mixed_pixel_edge
    with np.errstate(invalid="ignore"):  # inf - inf where neither hits: not an edge
        d_left = np.roll(image, 1, axis=1) - image
        d_right = np.roll(image, -1, axis=1) - image
    # A depth edge: one neighbour much farther, the other on the same surface. A surface seen
    # at a grazing angle has large steps on both sides (one nearer) and is not an edge.
    left_edge = (d_left > edge_m) & (np.abs(d_right) < edge_m / 2)
    right_edge = (d_right > edge_m) & (np.abs(d_left) < edge_m / 2)
    gap = np.minimum(np.where(left_edge, d_left, d_right), 2.0)  # no return beside it: up to 2 m
    edge = np.isfinite(image) & (left_edge | right_edge)
    edge &= rng.random(image.shape) < sensor.mixed_pixel_prob
    extra = np.zeros(image.shape)
    extra[edge] = rng.random(int(edge.sum())) * gap[edge]
    return extra.reshape(-1)
