"""Spinning-LiDAR beam layouts: one table of named sensors, read by the filter's beam model
(:mod:`pcc_ros.pipeline.beam_model`, :mod:`pcc_ros.pipeline.evidence`) and by the SynthCars
simulator (:mod:`pcc_ros.data.synthetic.lidar`), so a simulated ``vlp16`` and the filter's
``vlp16`` are the same sensor.

A layout is an ascending table of beam elevations (degrees, in the scan frame, the sensor at
its origin) and the azimuth step between two firings of one beam. Two units stacked at one
origin are the union of their tables (an elevation listed twice: two beams fire along it).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pcc_ros.errors import ConfigError


def linspace_blocks(*blocks: tuple[float, float, int]) -> tuple[float, ...]:
    """Elevations (degrees) of evenly spread laser blocks ``(first, last, beams)``, in the given
    order (the datasheets list them top first)."""
    return tuple(float(v) for first, last, beams in blocks for v in np.linspace(first, last, beams))


@dataclass(frozen=True)
class SensorModel:
    """A spinning LiDAR's beam geometry: every beam's elevation and the azimuth step.

    ``elevations_deg`` is sorted ascending on construction (any order is accepted: a driver's
    ring order, a datasheet's top-first list); ``azimuth_resolution_deg`` is the angle between
    two returns of one beam. The default is the Velodyne HDL-64E as mounted on KITTI's car.
    """

    elevations_deg: tuple[float, ...] = field(
        default_factory=lambda: linspace_blocks((2.0, -8.33, 32), (-8.83, -24.9, 32)))
    azimuth_resolution_deg: float = 0.1728
    name: str = ""

    def __post_init__(self) -> None:
        table = np.asarray(self.elevations_deg, dtype=np.float64).reshape(-1)
        if (
            len(table) < 2
            or not np.isfinite(table).all()
            or np.abs(table).max() >= 90.0
            or not np.isfinite(self.azimuth_resolution_deg)
            or not 0.0 < self.azimuth_resolution_deg <= 45.0
        ):
            raise ConfigError(f"bad sensor model {self.name or ''}: {len(table)} beams, elevations within "
                              f"[{table.min() if len(table) else 0}, {table.max() if len(table) else 0}] deg, "
                              f"azimuth step {self.azimuth_resolution_deg} deg (need >= 2 finite beams within "
                              "+-90 deg and a step in (0, 45] deg)")
        object.__setattr__(self, "elevations_deg", tuple(float(v) for v in np.sort(table)))

    @property
    def rings(self) -> int:
        """Number of beams."""
        return len(self.elevations_deg)

    @property
    def columns(self) -> float:
        """Firings of one beam per revolution."""
        return 360.0 / self.azimuth_resolution_deg

    def ring_elevations(self) -> np.ndarray:
        """Ascending beam elevations, radians."""
        return np.deg2rad(np.asarray(self.elevations_deg, dtype=np.float64))

    def top_first(self) -> np.ndarray:
        """Beam elevations in degrees, top beam first (the simulator's ray order)."""
        return np.asarray(self.elevations_deg, dtype=np.float64)[::-1].copy()

    def describe(self) -> str:
        """One line for logs: beams, elevation span, azimuth step."""
        e = self.elevations_deg
        return (f"{self.name + ': ' if self.name else ''}{self.rings} beams {e[0]:+.2f} .. {e[-1]:+.2f} deg, "
                f"azimuth step {self.azimuth_resolution_deg:.4g} deg")


#: Velodyne VLP-32C (user manual, vertical angles of lasers 0-31, sorted): dense near the horizon.
VLP32C_ELEVATIONS = (
    -25.0, -15.639, -11.31, -8.843, -7.254, -6.148, -5.333, -4.667, -4.0, -3.667, -3.333, -3.0, -2.667, -2.333,
    -2.0, -1.667, -1.333, -1.0, -0.667, -0.333, 0.0, 0.333, 0.667, 1.0, 1.333, 1.667, 2.333, 3.333, 4.667, 7.0,
    10.333, 15.0,
)
#: Hesai Pandar64 (nominal angle-correction table, sorted): 1/6 deg steps from -6 to +2 deg.
PANDAR64_ELEVATIONS = (
    -24.897, -18.889, -13.93, -12.974, -12.006, -11.032, -9.885, -9.06, -8.059, -7.063, -6.061, -5.898, -5.726,
    -5.565, -5.391, -5.229, -5.057, -4.892, -4.72, -4.558, -4.385, -4.221, -4.05, -3.884, -3.712, -3.548, -3.375,
    -3.21, -3.04, -2.873, -2.7, -2.536, -2.365, -2.198, -2.028, -1.86, -1.688, -1.522, -1.351, -1.184, -1.013,
    -0.844, -0.675, -0.508, -0.337, -0.164, 0.0, 0.169, 0.337, 0.508, 0.675, 0.846, 1.013, 1.184, 1.351, 1.522,
    1.688, 1.86, 2.028, 3.04, 5.057, 8.059, 11.032, 14.882,
)


def _uniform(top: float, bottom: float, beams: int) -> tuple[float, ...]:
    return linspace_blocks((top, bottom, beams))


#: Named sensors (datasheet values). Azimuth steps at 10 Hz unless the source records another
#: rate (nuScenes' HDL-32E spins at 20 Hz); Ouster's at 1024 columns per revolution.
SENSOR_PRESETS: dict[str, SensorModel] = {
    # Velodyne HDL-64E as on KITTI's car: two laser blocks, 2083 columns at 10 Hz.
    "hdl64": SensorModel(linspace_blocks((2.0, -8.33, 32), (-8.83, -24.9, 32)), 0.1728, "hdl64"),
    # Velodyne HDL-32E as on nuScenes: 1.33 deg steps, 1084 columns at 20 Hz.
    "hdl32": SensorModel(_uniform(10.67, -30.67, 32), 0.33, "hdl32"),
    # Velodyne VLP-16 (Puck): 2 deg steps, 0.2 deg at 10 Hz.
    "vlp16": SensorModel(_uniform(15.0, -15.0, 16), 0.2, "vlp16"),
    # Velodyne VLP-32C (Ultra Puck): non-uniform, 0.2 deg at 10 Hz.
    "vlp32c": SensorModel(VLP32C_ELEVATIONS, 0.2, "vlp32c"),
    # Two VLP-32C stacked on one mast, both upright (Argoverse 2's up / down lidars): every
    # elevation fires twice per step.
    "vlp32c_x2": SensorModel(VLP32C_ELEVATIONS * 2, 0.2, "vlp32c_x2"),
    # Ouster OS1-64 / OS1-128: uniform over +-22.5 deg, 1024 columns.
    "os1_64": SensorModel(_uniform(22.5, -22.5, 64), 360.0 / 1024, "os1_64"),
    "os1_128": SensorModel(_uniform(22.5, -22.5, 128), 360.0 / 1024, "os1_128"),
    # Hesai Pandar64: -25 .. +15 deg, 0.2 deg at 10 Hz.
    "pandar64": SensorModel(PANDAR64_ELEVATIONS, 0.2, "pandar64"),
}


def sensor_preset(name: str) -> SensorModel:
    """The named sensor of :data:`SENSOR_PRESETS`; an unknown name is a :class:`ConfigError` listing them."""
    try:
        return SENSOR_PRESETS[name]
    except KeyError:
        raise ConfigError(f"unknown sensor {name!r}; known: {sorted(SENSOR_PRESETS)}") from None
