"""splat_slam_ros: Splat-SLAM as a pip-installable ROS 2 Jazzy node graph."""
from setuptools import find_packages, setup

setup(
    package_dir={"splat_slam_ros": "splat_slam_ros", "splat_slam_nodes": "nodes",
                 "splat_slam_synth": "splat_slam_synth"},
    packages=find_packages(include=["splat_slam_ros", "splat_slam_ros.*"])
    + ["splat_slam_nodes", "splat_slam_nodes.tools", "splat_slam_synth"],
)
