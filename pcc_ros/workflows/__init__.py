"""The workflows: each module here is the library behind one ``pcc`` command.

A workflow (``train``, ``evaluate``, ``evaluate_real``, ``detection_eval``,
``filter_calibration``, ``filter_sensors``, ``filter_check``, ``demo``) takes a dataclass of
options, runs the job end to end on top of the lower floors (data, models, pipeline, metrics)
and returns or writes its results. The matching module in :mod:`pcc_ros.cli` parses the flags,
builds those options and calls it, so the same job runs from Python without a command line.
Workflows sit on top of the import layers (docs/ARCHITECTURE.md): only ``cli/`` imports them.
"""
