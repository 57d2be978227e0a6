"""A user's LiDAR as the simulator's sensor, read from the user's own scans.

The filter's reject threshold depends on the beam layout (``docs/filter.md``, "Per-sensor
thresholds"): the shipped file holds one per named preset and the most lenient for a sensor that
matches none. A user whose sensor is not among the presets calibrates its own threshold with
``pcc calibrate-filter --sensor-from SCANS``: this module reads a few of those scans (any source
:func:`~pcc_ros.data.sources.open_frames` reads: a bag, KITTI, nuScenes, Argoverse 2), estimates
the beam model as the node does (:func:`~pcc_ros.pipeline.beam_model.estimate_sensor`; from the
ring field when the driver publishes one) and the sensor's height above the ground, and returns
them as a SynthCars :class:`~pcc_ros.data.synthetic.lidar.Sensor`; the command then simulates
that sensor and sets the threshold by cross-validation over its streets, with no labelled frame.

Without a ring field the estimate holds the beams the scans show beyond 5 m: the steepest
downward beams and upward ones under open sky may be missing, and two stacked units firing along
one elevation read as one beam at half the azimuth step. The simulated sensor then lacks them too,
which changes little for the filter (those beams return nothing from a car's body beyond 5 m).
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import islice
from pathlib import Path

import numpy as np

from pcc_ros.data.sources import open_frames
from pcc_ros.data.synthetic.lidar import Sensor
from pcc_ros.errors import ConfigError, DataError
from pcc_ros.geometry.beams import SensorModel
from pcc_ros.pipeline.beam_model import (
    MATCH_DEG_RINGLESS,
    MATCH_MISSING,
    MOUNT_RANGE,
    estimate_sensor,
    ground_height,
    matching_preset,
    ring_column,
    same_layout,
)

#: Two scans' estimates agree when their beams lie within this many degrees and their azimuth
#: steps within this share (with a ring field: beam for beam); without one, a scan may show up
#: to this share of beams fewer or more (a beam with too few returns beyond 5 m in that scan, two
#: merged, one split): the tolerances with which a ring-less estimate is matched to a preset.
AGREE_DEG, AGREE_STEP, AGREE_MISSING = MATCH_DEG_RINGLESS, 0.05, MATCH_MISSING


@dataclass(frozen=True)
class ScannedSensor:
    """What the scans say about the sensor: its beam model, its height above the ground, how many
    scans agreed, and the preset it matches (None: no preset describes it)."""

    model: SensorModel
    mount_height: float
    scans: int
    agreeing: int
    preset: str | None
    source: str
    ring_field: bool

    def sensor(self, name: str = "scanned") -> Sensor:
        """The SynthCars sensor with this beam model and height (other settings: the defaults)."""
        return Sensor(layout=name, elevation_table=self.model.elevations_deg,
                      azimuth_step=self.model.azimuth_resolution_deg, mount_height=round(self.mount_height, 3))

    def describe(self) -> str:
        """One line: what was read, from how many scans, and the preset it matches."""
        m = self.model
        return (f"sensor read from {self.agreeing} of {self.scans} scan(s) of {self.source} "
                f"({'ring field' if self.ring_field else 'no ring field: beams estimated from the elevations'}): "
                f"{m.rings} beams, {m.elevations_deg[0]:+.2f} to {m.elevations_deg[-1]:+.2f} deg, azimuth step "
                f"{m.azimuth_resolution_deg:.4f} deg, {self.mount_height:.2f} m above the ground; matching preset: "
                f"{self.preset or 'none'}")

    def to_dict(self) -> dict:
        return {"source": self.source, "beams": self.model.rings, "elevations_deg": list(self.model.elevations_deg),
                "azimuth_step_deg": self.model.azimuth_resolution_deg, "mount_height_m": self.mount_height,
                "scans": self.scans, "agreeing": self.agreeing, "matching_preset": self.preset,
                "ring_field": self.ring_field}


def scanned_sensor(path: str | Path, scans: int = 5, sequence: str | None = None,
                   height: float | None = None) -> ScannedSensor:
    """The sensor of the first ``scans`` scans of ``path``: each scan's beam model estimated alone,
    the most common one kept when at least half of the scans agree with it, its height the median
    of the scans' ground heights, or ``height`` (metres above the ground) where the user knows it
    (scans that show little ground: a garage, a yard walled in).

    Raises :class:`ConfigError` when no scan shows a beam structure, the scans disagree (several
    sensors, or a merged cloud), or no ground is seen; :class:`DataError` when ``path`` holds no scan.
    """
    if scans < 1:
        raise ConfigError(f"--sensor-scans must be >= 1, got {scans}")
    if height is not None and not MOUNT_RANGE[0] <= height <= MOUNT_RANGE[1]:
        raise ConfigError(f"--sensor-height must be within {MOUNT_RANGE[0]}-{MOUNT_RANGE[1]} m, got {height}")
    models, heights, read, rings_seen = [], [], 0, False
    for sample in islice(open_frames(path, sequence), scans):
        read += 1
        points = np.asarray(sample.points)
        rings = ring_column(points, sample.fields)
        rings_seen |= rings is not None
        model = estimate_sensor(points, rings)
        if model is not None:
            models.append(model)
        ground = ground_height(points) if height is None else height
        if ground is not None:
            heights.append(ground)
    if read == 0:
        raise DataError(f"{path}: no scans to read the sensor from")
    if not models:
        raise ConfigError(f"{path}: none of {read} scan(s) shows a spinning LiDAR's beam structure "
                          "(a merged or motion-compensated cloud?); give the sensor as a preset instead")
    missing = 0.0 if rings_seen else AGREE_MISSING
    agree = [sum(same_layout(m, ref, AGREE_DEG, AGREE_STEP, missing) for m in models) for ref in models]
    best = int(np.argmax(agree))
    if 2 * agree[best] < read:
        raise ConfigError(f"{path}: the beam models of {read} scans disagree (at most {agree[best]} agree): "
                          "several sensors in one cloud, or scans from different sensors")
    if not heights:
        raise ConfigError(f"{path}: no ground seen around the sensor in {read} scan(s) (scans in the sensor's own "
                          "frame? give its height with --sensor-height)")
    model = SensorModel(models[best].elevations_deg, models[best].azimuth_resolution_deg, "scanned")
    return ScannedSensor(model, float(np.median(heights)), read, agree[best], matching_preset(model), str(path),
                         rings_seen)
