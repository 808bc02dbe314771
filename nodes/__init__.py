"""splat_slam_nodes: the Splat-SLAM stage nodes as ROS 2 processes (tracker, depth, loop
closure, mapper) and the ROS plumbing they share (message conversion, QoS, camera input, TF
frames, services). The tools that start, feed and watch them: :mod:`splat_slam_nodes.tools`."""
