"""pcc_ros: LiDAR vehicle shape completion and shape-based detection filtering for ROS 2.

``import pcc_ros`` must stay light and must never need ROS: heavy libraries (torch,
open3d, rosbags) are imported by the modules that use them, and rclpy only inside
``pcc_ros.nodes``.
"""

__version__ = "0.1.0"
