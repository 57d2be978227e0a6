"""SynthCars: a simulated 64-beam LiDAR street world written as KITTI tracking data.

Procedural vehicles with exact shapes, an HDL-64E-like ray-cast sensor, street scenes
with traffic and detector-fooling clutter, a simulated detector, and a writer for the
KITTI tracking devkit layout plus the complete canonical shape of every labelled car.
See ``docs/synthcars.md``.
"""

from pcc_ros.data.synthetic.generator import generate, load_shape

__all__ = ["generate", "load_shape"]
