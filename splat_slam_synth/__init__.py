"""Synthetic RGB-D sequences in the TUM layout, driven by real recorded camera trajectories.

The scene generator, installed beside the library (``splat_slam_ros``, whose types, geometry
and trajectory files it uses); its command is ``splat-slam-synth`` (``cli``).

``generate_sequence`` samples N camera frames at ``fps`` along a trajectory (TUM, KITTI,
EuRoC or the built-in hand-held path), fits a textured room with furniture-like boxes
around it, renders RGB + exact z-depth by vectorised ray casting (analytic ray/box slab
intersections, trilinear mip-mapped textures, Lambertian shading with contact shadows)
and writes::

    OUT/rgb/<t>.png  OUT/depth/<t>.png (uint16, 5000 per metre)  OUT/rgb.txt  OUT/depth.txt
    OUT/groundtruth.txt (TUM, camera-to-world, the exact pose each frame was rendered with)
    OUT/intrinsics.yaml (Intrinsics.to_yaml + depth_scale, fps, generation record)

``scene`` picks the content (``SCENES``): the default furnished ``room`` or a variant made
to stress flow / depth (``low_texture``, ``tiled``, ``repetitive``, ``thin``, ``deep``; see
the ``variants`` module). Camera realism (motion blur, rolling shutter, auto-exposure drift,
vignetting, shot/read noise, JPEG; presets ``realistic`` and ``harsh``) is applied to RGB
only; depth stays clean for evaluation.

Conventions follow ``splat_slam_ros.types``: poses camera-to-world, OpenCV camera axes (x right,
y down, z forward), pixel centres at integer coordinates. Internally the scene lives in a
"room frame" (z up, origin at the mean camera position); ``Scene.T_room_world`` maps
world points into it.

Modules: ``options`` (constants, errors, realism settings), ``trajectories`` (built-in path,
file loading, interpolation), ``textures``, ``scene`` (room + boxes fitted to a trajectory),
``variants`` (the other scenes),
``render`` (ray casting), ``camera`` (photometric effects), ``sequence`` (plan + write) and
``cli`` (the command line).
"""
from splat_slam_synth.camera import CameraEffects
from splat_slam_synth.options import (DEPTH_SCALE, GAP_WARN_S, REALISM_PRESETS, SCENES,
                                     TEX_LEVELS, TEX_SIZE, RealismOptions, SynthError,
                                     check_scene, default_intrinsics, parse_size,
                                     resolve_realism)
from splat_slam_synth.render import render_frame
from splat_slam_synth.scene import Scene, make_scene
from splat_slam_synth.variants import build_scene
from splat_slam_synth.sequence import (SequencePlan, depth_to_png16, generate_sequence,
                                      plan_sequence, rolling_shutter_bands)
from splat_slam_synth.textures import PROCEDURAL, procedural_texture
from splat_slam_synth.trajectories import (PoseInterpolator, builtin_trajectory, estimate_up,
                                          frame_stamps, load_trajectory)

__all__ = [
    "CameraEffects", "DEPTH_SCALE", "GAP_WARN_S", "REALISM_PRESETS", "TEX_LEVELS", "TEX_SIZE",
    "RealismOptions", "SCENES", "SynthError", "check_scene", "default_intrinsics", "parse_size",
    "resolve_realism", "render_frame", "Scene", "build_scene", "make_scene", "SequencePlan",
    "depth_to_png16", "generate_sequence", "plan_sequence", "rolling_shutter_bands",
    "PROCEDURAL", "procedural_texture", "PoseInterpolator",
    "builtin_trajectory", "estimate_up", "frame_stamps", "load_trajectory",
]
