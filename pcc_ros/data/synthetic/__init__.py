"""SynthCars: a simulated 64-beam LiDAR street world written as KITTI tracking data.

Procedural vehicles with exact shapes, an HDL-64E-like ray-cast sensor, street scenes
with traffic and detector-fooling clutter, a simulated detector, and a writer for the
KITTI tracking devkit layout plus the complete canonical shape of every labelled car.
See ``docs/synthcars.md``.
"""

__all__ = ["generate", "load_families", "load_shape"]


def __getattr__(name: str):
    """Import the generator (and open3d) only when it is used, not on ``pcc --help``."""
    if name in ("load_families", "load_shape"):  # file readers: no simulator (open3d) needed
        from pcc_ros.data.synthetic import reading

        return getattr(reading, name)
    if name in __all__:
        from pcc_ros.data.synthetic import generator

        return getattr(generator, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
