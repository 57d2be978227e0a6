"""ROS 2 node shells over :mod:`pcc_ros.pipeline.core` — the only modules that import rclpy.

rclpy is imported lazily (inside ``main()`` and :mod:`pcc_ros.nodes.ros_node`), so these
modules import, and build their parameter tables, on machines without ROS.
"""
