"""splat_slam_ros: Splat-SLAM as a pip-installable ROS 2 Jazzy node graph."""
from setuptools import setup

setup(
    package_dir={"splat_slam_ros": "splat_slam_ros", "splat_slam_nodes": "nodes"},
    packages=["splat_slam_ros", "splat_slam_ros.cli", "splat_slam_ros.rasterizer", "splat_slam_nodes"],
)
