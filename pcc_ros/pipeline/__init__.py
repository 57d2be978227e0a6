"""The per-frame pipeline: :mod:`~pcc_ros.pipeline.config` (the one parameter table,
``PipelineConfig``, YAML loading), :mod:`~pcc_ros.pipeline.core` (``Pipeline``,
``FrameResult``, the output messages) and :mod:`~pcc_ros.pipeline.filter` (the evidence /
shape-mismatch detection filter).

Import the submodules directly; this ``__init__`` imports nothing.
"""
