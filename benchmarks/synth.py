"""SynthCars generation speed: full 64-beam frames per second (target >= 5 on 2 cores).

Three figures, measured in this process on the same street:
- ``raycast``: baseline, open3d scene built from the whole frame and cast (~133k rays), the
  naive per-frame approach (the generator keeps the static street's scene across frames);
- ``frame``: a whole frame (scene assembly, ray cast, sensor effects, labels, simulated
  detector, writing the scan / label / detection files): ``frames_per_s``;
- ``generate``: ``pcc synth`` end to end for one sequence (street, frames, ground-truth
  shapes, meta.json): ``frames_per_s_end_to_end``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import open3d as o3d

from benchmarks.common import print_table


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--frames", type=int, default=20, help="frames per measurement (default 20)")


def run(args: argparse.Namespace) -> dict:
    from pcc_ros.data.synthetic import generate, writer
    from pcc_ros.data.synthetic.generator import build_sequence, sensor_pose, simulate_frame
    from pcc_ros.data.synthetic.lidar import Sensor, build_scene

    frames = max(2, int(args.frames))
    sensor = Sensor()
    street = build_sequence(args.seed, 0, frames, "train")
    calib = writer.calibration()

    # Baseline: the ray cast alone, same rays and scene as a frame.
    cast_s = []
    for f in range(frames):
        origin, _ = sensor_pose(street, f, sensor)
        world, _ = street.world_at(f, near=origin[:2])
        rays = np.empty((sensor.n_rays, 6), np.float32)
        rays[:, :3], rays[:, 3:] = origin, sensor.directions
        start = time.perf_counter()
        build_scene(world).cast_rays(o3d.core.Tensor(rays))
        cast_s.append(time.perf_counter() - start)
    n_triangles = len(world.triangles)

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        frame_s, n_points = [], []
        for f in range(frames):
            start = time.perf_counter()
            res = simulate_frame(street, f, sensor, np.random.default_rng(f))
            writer.write_bin(out / "velodyne" / f"{f:06d}.bin", res.scan.points)
            writer.write_text(out / "det" / f"{f:06d}.txt", writer.detection_lines(res.detections, calib))
            writer.write_text(out / "lab" / f"{f:06d}.txt", writer.tracking_label_lines(res.gt, f, res.occluded, calib))
            frame_s.append(time.perf_counter() - start)
            n_points.append(len(res.scan.points))
        start = time.perf_counter()
        generate(out / "full", 1, frames, args.seed, sensor=sensor, progress=False)
        end_to_end = time.perf_counter() - start

    raycast_ms = float(np.median(cast_s) * 1e3)
    frame_ms = float(np.median(frame_s) * 1e3)
    rows = [
        {"stage": "naive: build + cast whole scene (baseline)", "ms/frame": raycast_ms,
         "frames/s": 1e3 / raycast_ms, "ratio": 1.0},
        {"stage": "frame (simulate + write)", "ms/frame": frame_ms, "frames/s": 1e3 / frame_ms,
         "ratio": frame_ms / raycast_ms},
        {"stage": "generate end to end", "ms/frame": end_to_end / frames * 1e3, "frames/s": frames / end_to_end,
         "ratio": end_to_end / frames * 1e3 / raycast_ms},
    ]
    print_table(f"pcc bench synth: {frames} full 64-beam frames, {sensor.n_rays} rays, "
                f"{n_triangles} triangles, {int(np.mean(n_points))} points/frame", rows)
    return {
        "frames_per_s": 1e3 / frame_ms,
        "frames_per_s_end_to_end": frames / end_to_end,
        "raycast_ms": raycast_ms,
        "frame_ms": frame_ms,
        "rays": sensor.n_rays,
        "triangles": n_triangles,
        "points_per_frame": float(np.mean(n_points)),
        "frames": frames,
        "target_frames_per_s": 5.0,
    }
