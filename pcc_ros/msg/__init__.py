"""The message layer: every ROS message pcc_ros touches goes through here.

Modules (import the one you need; none imports rclpy):

* :mod:`~pcc_ros.msg.typestore` - rosbags Jazzy type store + vision_msgs 4.x, RIHS01 hashes,
  class-flavour-neutral message construction (``classes`` resolver, ``None`` = rosbags);
* :mod:`~pcc_ros.msg.stamps` - ``builtin_interfaces/Time`` <-> integer nanoseconds, headers;
* :mod:`~pcc_ros.msg.pointcloud2` - PointCloud2 <-> numpy (zero-copy views, fast xyz);
* :mod:`~pcc_ros.msg.detections` - Detection3DArray / MarkerArray <-> :class:`~pcc_ros.types.Boxes`.

All of them raise :class:`pcc_ros.errors.MessageError` on malformed input.
"""
