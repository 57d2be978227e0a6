"""Exception hierarchy.

Every error the package raises on bad *input* derives from :class:`PccError`, so a
running node can catch exactly these, log the message and skip the frame, while
programming errors still surface as ordinary exceptions.
"""


class PccError(Exception):
    """Base class for all input-related errors raised by pcc_ros."""


class MessageError(PccError):
    """A ROS message (PointCloud2, Detection3DArray, MarkerArray ...) is malformed."""


class DataError(PccError):
    """A dataset file (KITTI, nuScenes, SynthCars, bag) is missing, truncated or malformed."""


class CheckpointError(PccError):
    """A model checkpoint is missing, corrupt, truncated or does not match its config."""


class BackendError(PccError):
    """A completion backend produced unusable output (wrong shape, no finite point) for some input."""


class ConfigError(PccError):
    """A configuration value (YAML file, parameter, CLI flag) is invalid."""
