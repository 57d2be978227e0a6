"""ROS 2 bags: dataset conversion (``pcc convert``), summaries (``pcc info``) and reading back.

- :func:`pcc_ros.bags.convert.write_bag` - frames -> rosbag2 (MCAP + zstd, or sqlite3);
- :func:`pcc_ros.bags.read.read_frames` - rosbag2 -> frames, for the offline tools.

Import the submodules directly; this package imports nothing heavy at import time.
"""
