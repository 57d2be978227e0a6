"""The per-frame pipeline: :mod:`~pcc_ros.pipeline.config` (the node parameter table),
:mod:`~pcc_ros.pipeline.core` (``Pipeline``, ``FrameResult``, the output messages) and
:mod:`~pcc_ros.pipeline.filter` (the shape-mismatch / evidence filter).

Import the submodules directly; this ``__init__`` imports nothing (no torch, no numpy).
"""
