"""Where the package's resources and the sample data live, in a checkout and in an install.

One place for this, so a checkout (``pip install -e``), a pip install and a colcon install
(``share/pcc_ros``) all resolve the same way.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

#: The repository root when running from a source checkout.
SOURCE_ROOT = Path(__file__).resolve().parents[1]


def shared_data_dir() -> Path:
    """The real sample data (KITTI, nuScenes) beside the repository: ``../shared/data``.

    ``PCC_SHARED_DATA`` overrides it. The folder may not exist (a pip install, a user's
    machine); callers check and skip or ask for a path.
    """
    override = os.environ.get("PCC_SHARED_DATA")
    return Path(override) if override else SOURCE_ROOT.parent / "shared" / "data"


def share_dirs() -> list[Path]:
    """Candidate ``share/pcc_ros`` folders of installs (pip prefix, colcon / ament prefixes)."""
    prefixes = [sys.prefix, sys.base_prefix, *os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep)]
    return [Path(p) / "share" / "pcc_ros" for p in dict.fromkeys(prefixes) if p]


def resource_dir(name: str) -> Path | None:
    """``config`` / ``launch`` of the checkout, else of an install's ``share/pcc_ros``; None if absent."""
    for folder in [SOURCE_ROOT / name, *(d / name for d in share_dirs())]:
        if folder.is_dir():
            return folder
    return None
