"""Exception hierarchy: one error type per layer.

Every error the package raises on bad *input* derives from :class:`PccError`, so a
running node can catch exactly these, log the message and skip the frame, while
programming errors still surface as ordinary exceptions.

Layers and their errors:

- :class:`MessageError`: one ROS message (PointCloud2, Detection3DArray, ...) is malformed;
- :class:`DataError`: a dataset file (KITTI, nuScenes, SynthCars, instance cache); its
  subclass :class:`BagError` for a rosbag2 (MCAP / sqlite3) that is damaged or unusable;
- :class:`CheckpointError`: a model checkpoint;
- :class:`BackendError`: a completion backend's output;
- :class:`TrainingError`: a training run that cannot go on (non-finite loss);
- :class:`ConfigError`: a parameter, YAML file or CLI flag.

Messages name the input first (``<file>[:line|@offset]: <what>``); an optional ``hint``
says what to do and is appended as ``" — <hint>"``, which is the form the ``pcc`` tool
prints: ``ERROR pcc: <file>[:line|@offset]: <what> — <what to do>``.
"""

from __future__ import annotations


class PccError(Exception):
    """Base class for all input-related errors raised by pcc_ros.

    ``PccError(message, hint="what to do")``: ``str()`` is ``"message — hint"``.
    """

    def __init__(self, message: str = "", *, hint: str = "") -> None:
        super().__init__(message)
        self.message = str(message)
        self.hint = str(hint)

    def __str__(self) -> str:
        return f"{self.message} — {self.hint}" if self.hint else self.message


class MessageError(PccError):
    """A ROS message (PointCloud2, Detection3DArray, MarkerArray ...) is malformed."""


class DataError(PccError):
    """A dataset file (KITTI, nuScenes, SynthCars, bag, instance cache) is missing, truncated or malformed."""


class BagError(DataError):
    """A rosbag2 is damaged (chunk CRC, compression, sqlite integrity) or has unusable topics."""


class CheckpointError(PccError):
    """A model checkpoint is missing, corrupt, truncated or does not match its config."""


class BackendError(PccError):
    """A completion backend produced unusable output (wrong shape, no finite point) for some input."""


class TrainingError(PccError):
    """Training cannot go on (a non-finite loss: diverged, or bad data that validation missed)."""


class ConfigError(PccError):
    """A configuration value (YAML file, parameter, CLI flag) is invalid."""
