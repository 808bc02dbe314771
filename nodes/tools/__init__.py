"""The graph's tools: the launcher (splat-slam-launch) and its helpers, the bag player, the
camera driver, the rerun logger and splat-slam-topic. They start, feed, watch or record the
stage nodes (splat_slam_nodes); no stage node imports them."""
