"""Evaluation of a run against ground truth: metrics over arrays, maps and files.

``trajectory`` (ATE, RPE, Sim(3) alignment, segment scales), ``image`` (PSNR, SSIM, exposure
compensation), ``perceptual`` (LPIPS), ``depth`` (depth L1, depth-edge band), ``mesh``
(accuracy / completion), ``rendering`` (the rendered views of a map), ``map_sequence`` (the
mapper alone on ground truth), ``run`` (the metrics.json entries of a finished run) and
``files`` (trajectory files in, JSON and plots out: what ``splat-slam-eval`` does).
``inputs`` holds the checked conversions they share and
:class:`~splat_slam_ros.evaluation.inputs.MetricError`.
"""
