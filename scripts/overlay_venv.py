"""Make a second venv see a first one's packages beneath its own (``make test-numpy1``).

    OVERLAY/bin/python scripts/overlay_venv.py BASE_VENV

Writes ``pcc_ros_overlay.pth`` into the overlay's site-packages: the base venv's site-packages
are added after the overlay's own (so the overlay's numpy 1.26 wins), with the base's ``.pth``
hooks run; the ROS 2 wheels' libraries (``ros_*.libs``, ``lib``) and the base prefix (its
ament index: vision_msgs built there) are put on ``LD_LIBRARY_PATH`` / ``AMENT_PREFIX_PATH``
first, because those hooks derive them from the running prefix, which is the overlay's.
"""

from __future__ import annotations

import sys
import sysconfig
from pathlib import Path


def main() -> int:
    base = Path(sys.argv[1]).resolve()
    version = f"python{sys.version_info.major}.{sys.version_info.minor}"
    base_site = base / "lib" / version / "site-packages"
    if not base_site.is_dir():
        print(f"{base_site}: not a venv's site-packages of this Python ({version})", file=sys.stderr)
        return 1
    libs = [str(p) for p in sorted(base_site.glob("ros_*.libs"))] + [str(base / "lib")]
    line = (
        "import os, site; "
        f"os.environ['LD_LIBRARY_PATH'] = os.pathsep.join({libs!r} + [os.environ.get('LD_LIBRARY_PATH', '')]); "
        f"os.environ['AMENT_PREFIX_PATH'] = os.pathsep.join(p for p in ({str(base)!r}, "
        "os.environ.get('AMENT_PREFIX_PATH', '')) if p); "
        f"site.addsitedir({str(base_site)!r})\n"
    )
    target = Path(sysconfig.get_paths()["purelib"]) / "pcc_ros_overlay.pth"
    target.write_text(line)
    print(f"{target}: {base_site} beneath this venv's packages")
    return 0


if __name__ == "__main__":
    sys.exit(main())
