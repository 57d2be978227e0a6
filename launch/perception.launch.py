"""Start completion_node and detection_filter_node with their parameter files.

    ros2 launch pcc_ros perception.launch.py points:=/velodyne_points detections:=/detector/boxes
    ros2 launch pcc_ros perception.launch.py backend:=mirror use_sim_time:=true   # with `ros2 bag play --clock`
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description() -> LaunchDescription:
    share = get_package_share_directory("pcc_ros")
    points = LaunchConfiguration("points")
    detections = LaunchConfiguration("detections")
    use_sim_time = LaunchConfiguration("use_sim_time")
    backend = LaunchConfiguration("backend")
    common = {"use_sim_time": use_sim_time, "backend": backend}
    remaps = [("points", points), ("detections", detections)]
    return LaunchDescription(
        [
            DeclareLaunchArgument("points", default_value="/points", description="input PointCloud2 topic"),
            DeclareLaunchArgument("detections", default_value="/detections", description="input Detection3DArray"),
            DeclareLaunchArgument("use_sim_time", default_value="false", description="use /clock (bag replay)"),
            DeclareLaunchArgument("backend", default_value="pointpncnet", description="completion backend"),
            Node(
                package="pcc_ros",
                executable="completion_node",
                name="completion_node",
                parameters=[os.path.join(share, "config", "completion.yaml"), common],
                remappings=remaps,
                output="screen",
            ),
            Node(
                package="pcc_ros",
                executable="detection_filter_node",
                name="detection_filter_node",
                parameters=[os.path.join(share, "config", "detection_filter.yaml"), common],
                remappings=remaps,
                output="screen",
            ),
        ]
    )
