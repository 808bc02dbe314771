"""One configuration schema for the in-process pipeline and the ROS 2 nodes.

Every stage reads its own section. YAML files in ``config/`` override the
defaults below (which follow the reference implementation, see
``../shared/notes/reference-defaults.md``); ROS node parameters use the same
dotted names (``tracking.keyframe_thresh``...).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any, Dict, Optional

import yaml


class ConfigError(ValueError):
    """A user-facing configuration mistake (unknown key, wrong type, bad file)."""


# mapping.raster_backend values (the rasterizer's BACKENDS; tests/test_raster_backend.py)
RASTER_BACKENDS = ("auto", "cpp", "torch", "gsplat")
BA_BACKENDS = ("auto", "cpp", "torch")    # tracking.ba_backend (tracking/dense_ba.py)


@dataclass
class CameraConfig:
    """Input images: crop, undistortion, rolling shutter and the processing (mapping) size."""

    # Processing (tracking + mapping) image size after crop/resize. 0 x 0 = auto: the input
    # size, shrunk (aspect kept, sides multiples of 16) to at most max_pixels pixels.
    width: int = 0
    height: int = 0                  # processing height (see width; 0 x 0 = auto)
    max_pixels: int = 76800      # auto rule's limit: 320x240 for 2 cores (0 = keep input size)
    crop: int = 0                # pixels cropped from every border before resize
    undistort: bool = True       # undistort when the camera has distortion coefficients
    rolling_shutter_ms: float = 0.0  # readout top -> bottom row, ms (0 = global shutter)
    rolling_shutter_stamp_row: float = 0.5  # row an image stamp gives: 0 top, 1 bottom (synth)

    def processing_size(self, width: int, height: int) -> tuple:
        """(width, height) to resize a cropped ``width`` x ``height`` input to; (0, 0) keeps
        it. An explicit camera.width/height wins; else the auto rule above applies."""
        if self.width > 0 or self.height > 0 or self.max_pixels <= 0:
            return int(self.width), int(self.height)
        if width * height <= self.max_pixels:
            return 0, 0
        s = (self.max_pixels / float(width * height)) ** 0.5
        return max(16, int(width * s) // 16 * 16), max(16, int(height * s) // 16 * 16)


@dataclass
class TrackingConfig:
    """Camera tracking (paper 3.1): optical flow, keyframes, local and global bundle
    adjustment (BA), loop closure and DSPO."""

    device: str = "auto"                 # "auto" (CUDA when torch sees it), "cpu", "cuda"
    threads: int = 1                     # torch/OpenCV threads while tracking (0 = unchanged)
    # Tracking image size, apart from the mapping size (camera.*): the cropped input shrunk
    # (aspect kept, sides multiples of 16) to at most max_pixels pixels, but never smaller
    # than the mapping image; 0 = the input size, -1 = the mapping size. Keyframes are handed
    # on at the mapping size (image + intrinsics) with the disparity at this size's BA grid.
    # 110592 (640x480 -> 384x288): little better (fr2/desk 0.176 cm either way) for ~25 % more
    # tracking CPU with the default flow settings: opt-in (docs/tracking.md "Tracking size").
    max_pixels: int = -1
    ba_downsample: int = 8               # BA resolution = tracking image / this (paper: 1/8)
    # BA terms per edge: "cpp" the C++ kernel (CPU), "torch" the reference, "auto" the kernel
    # on CPU when it loads (metrics.json ba_backend says which ran and why)
    ba_backend: str = field(default="auto", metadata={"choices": BA_BACKENDS})
    # flow front end (classical stand-in for the paper's learned flow, see flow_frontend.py)
    flow_method: str = "dis_medium"      # OpenCV DIS preset: dis_ultrafast | dis_fast | dis_medium
    flow_downsample: int = 2             # DIS runs at tracking image / this (must divide ba_downsample)
    # threads computing DIS flows: 2 = a pair's forward and backward halves (and the batch of
    # next-keyframe flows) in parallel on two cores, same results; 1 = all in the tracking thread
    flow_workers: int = 2
    # DIS settings over the preset (-1 = the preset's). The defaults compute the flow at the
    # DIS input's own resolution (finest scale 0; the medium preset stops one level coarser)
    # from 8x8 patches every 4 px without the variational smoothing: 2-6x lower ATE than the
    # medium preset (docs/tracking.md "Flow settings"). Stride 8 (independent patches) is
    # faster and more accurate on smooth renders but loses real 1 Hz frames (fr3 sample)
    flow_finest_scale: int = 0
    flow_patch_stride: int = 4           # DIS patch stride (px at the DIS input; -1 = the preset's)
    flow_refine_iters: int = 0           # DIS variational refinement iterations (-1 = the preset's)
    fb_consistency_px: float = 1.0       # forward-backward error scale for confidences (tracking px)
    photo_sigma: float = 30.0            # photometric residual scale for confidences (grey levels)
    texture_grad: float = 1.0            # gradient (grey/px) at which a cell counts as textured
    flow_spread_px: float = 1.5          # flow spread inside a BA cell that halves its weight
    # per axis, the forward-backward error and spread along the other axis count only as far
    # as the image has texture along it (an edge's flow along itself is not measured: low-
    # texture scenes keep the weight of their edges; false = one isotropic confidence)
    flow_aperture: bool = True
    # learned front end (paper 3.1): DROID-SLAM checkpoint in the public layout; "" = DIS
    flow_model: str = ""                 # path to droid.pth (needs ba_downsample 8)
    flow_device: str = "auto"            # where the network runs: auto | cpu | cuda
    flow_model_iters: int = 4            # GRU update iterations per flow pair
    # motion filter / keyframes. Flow thresholds are in "reference BA pixels": BA-grid pixels
    # of a camera whose BA-grid focal length is 65.625 px (fx 525 at 1/8, the reference's
    # 640x480 TUM setting); they are scaled by (fx / ba_downsample) / 65.625, so one value
    # means the same viewing-angle change at any image size.
    motion_filter_thresh: float = 4.0    # keyframe candidate if mean flow to the last keyframe above
    keyframe_thresh: float = 4.0         # tau: candidate dropped if its BA-induced flow stays below
    # keyframe rate bound: on fast motion a candidate waits until fewer than max_keyframe_rate
    # keyframes were made in the last second of input and the last keyframe is
    # min_keyframe_interval old; fast motion (keyframe_urgent_flow) passes the budget, not the
    # interval, and is not counted (nor is the warm-up); a view that is leaving
    # (keyframe_urgent_valid) passes both
    max_keyframe_rate: float = 6.0       # keyframes in any second of input (0 = no bound)
    min_keyframe_interval: float = 0.125 # stream seconds between keyframes at least (0 = none)
    keyframe_urgent_flow: float = 2.0    # fast: mean flow above this x motion_filter_thresh
    # leaving: confident flow cells below this x their typical fraction (a candidate then even
    # below motion_filter_thresh: the reference is refreshed before the flow fails; 0 = off)
    keyframe_urgent_valid: float = 0.7
    # lost for this many frames in a row: initialise again from the current frame, the new segment
    # placed where the motion before the loss leads, with the last keyframe's depth scale (0 = never)
    reinit_after: int = 10
    warmup: int = 8                      # most keyframes collected before initialisation
    init_min_keyframes: int = 2          # initialise from this many keyframes once ...
    init_parallax: float = 1.5           # ... first -> newest shows this much parallax (upper-
                                         # quartile flow residual after the best homography,
                                         # ref. BA px; 0 = init at init_min_keyframes)
    init_iters: int = 15                 # BA iterations of the initialisation
    frontend_window: int = 12            # keyframes in the local BA window (reference: 25)
    frontend_radius: int = 1             # edges to the 2nd .. this-th previous keyframe (1 = none)
    frontend_max_factors: int = 36       # (reference: 75; CPU budget)
    frontend_thresh: float = 16.0        # proximity edges: induced mean flow below (ref. BA px)
    frontend_new_edges: int = 3          # proximity edge pairs added per new keyframe
    frontend_nms: int = 1                # proximity edges: suppression radius (keyframe ids)
    max_edge_age: int = 50               # drop non-consecutive BA edges after this many BA rounds
    ba_iters: int = 2                    # local BA iterations per keyframe
    pose_iters: int = 4                  # pose-only iterations per frame
    # a keyframe cell counts fully in a frame's pose fit once the keyframe's own edges saw it
    # with this flow confidence, in proportion below: a cell they never saw (the view entering
    # on fast motion) has a filled-in disparity that bent the pose (0 = every cell alike)
    pose_ref_conf: float = 0.2
    # flows matched at a wrong period (repetitive textures): a frame whose pose fit leaves more than
    # flow_pred_rms_px is fitted again without the cells far from its constant-velocity pose's flow
    flow_pred_gate: float = 1.0          # far: more than this from it (reference BA px; 0 = off)
    flow_pred_agree: float = 0.3         # only if this fraction of the confident weight is near it
    flow_pred_rms_px: float = 0.8        # refit above this pose-fit rms (tracking px)
    robust_huber_px: float = 0.5         # Huber threshold on BA residuals, tracking px (tracking.md)
    lost_min_valid: float = 0.12         # lost if fewer BA cells than this have a usable flow
    # ... or, on a view with little texture, fewer than this x the cells its texture could
    # make confident at most (never below lost_min_valid / 4; 0 = off)
    lost_rel_texture: float = 0.25
    lost_rms: float = 1.0                # lost if the frame's pose fit leaves this rms (BA px)
    reloc_keyframes: int = 4             # recent keyframes tried when the last one fails
    # the first frame after a keyframe (no earlier flow to it): DIS starts from the flow the
    # constant-velocity pose induces, not from zero (repetitive textures alias otherwise)
    predict_first_flow: bool = True
    # live input: up to this many frames skipped while the tracker was busy are kept (thinned
    # over a longer gap) until the next frame is tracked; when that frame's flow fails on the
    # motion since the last tracked one, or is weak (below keyframe_urgent_valid x the typical
    # confident fraction), the skipped frame halfway is tracked first (bisection; 0 = off)
    bridge_frames: int = 16
    filler_iters: int = 3                # pose-only iterations per non-keyframe at the end
    max_stored_flows: int = 20000        # newest frames whose flow is kept for that refinement
    # at the keyframe that ends the warm-up, the newest this many warm-up frames also get a
    # flow from it (aligned against both keyframes at the end; 0 = all): after a long slow
    # start the tracker's initialisation step stays short (live input skips less)
    next_kf_flows: int = 16
    event_pose_thresh: float = 1e-4      # report a keyframe if it moved more (scene units / rad)
    event_disp_thresh: float = 1e-3      # ... or its mean relative disparity change exceeds this
    # loop closure (paper 3.1 "Loop Closure")
    loop_closure: bool = True
    loop_window: int = 12                # active keyframes checked / optimised (reference: 25)
    loop_flow_thresh: float = 25.0       # tau_loop (BA px, flow induced by the current estimate)
    loop_time_gap: int = 20              # tau_t (keyframes)
    loop_nms: int = 12                   # loop candidates: suppression radius (keyframe ids)
    loop_max_edges: int = 2              # loop candidates measured per step
    loop_ba_iters: int = 2               # BA iterations of a loop closure
    loop_fit_rms: float = 0.25           # BA px: a loop edge already fitting this well needs no loop BA
    # online global BA (paper 3.1 "Global BA")
    global_ba: bool = True
    global_ba_every: int = 20            # keyframes
    global_ba_iters: int = 3             # BA iterations of one online global BA
    global_ba_radius: int = 2            # temporal edges: k <-> k-1, k -> k-2 .. k-radius
    global_ba_thresh: float = 12.0       # spatial edges: induced mean flow below (BA px)
    global_ba_max_edges: int = 2         # spatial edge pairs per new keyframe at most
    merge_flow: float = 4.0              # merge a settled revisit keyframe into an older one this close (ref BA px, 0 = off)
    edge_gate_px: float = 16.0           # temporal edges: drop cells this far from the estimate (tracking px)
    final_ba_iters: tuple = (7, 12)      # final global BA at the end: iterations of each pass
    keyframe_buffer: int = 512           # newest keyframes whose images the loop closure keeps
    # DSPO (paper Eq. 2); only active when a mono depth model is configured
    dspo: bool = True
    dspo_alpha1: float = 0.01            # a1: mono prior weight on high-error disparities
    dspo_alpha2: float = 0.1             # a2: mono prior weight on low-error disparities
    dspo_mono_thresh: float = 0.1        # skip DSPO where the mono fit errs more (x mean disparity)

    def processing_size(self, camera: CameraConfig, width: int, height: int) -> tuple:
        """(width, height) of the tracking image for a cropped ``width`` x ``height`` input;
        (0, 0) keeps it (``max_pixels`` above; compare ``CameraConfig.processing_size``)."""
        mw, mh = camera.processing_size(width, height)
        if self.max_pixels < 0:
            return int(mw), int(mh)
        if mw > 0 or mh > 0:         # the mapping size (ImagePreprocessor keeps the aspect)
            aw = mw if mw > 0 else round(width * mh / height)
            ah = mh if mh > 0 else round(height * mw / width)
        else:
            aw, ah = width, height
        if self.max_pixels == 0 or width * height <= self.max_pixels:
            return 0, 0
        s = (self.max_pixels / float(width * height)) ** 0.5
        tw = max(16, int(width * s + 1e-6) // 16 * 16)
        th = max(16, int(height * s + 1e-6) // 16 * 16)
        return (tw, th) if tw * th >= aw * ah else (int(mw), int(mh))


@dataclass
class DepthConfig:
    """Proxy depth of each keyframe (paper 3.2): multi-view filtered BA depth, optionally
    completed by a monocular depth model or a dense multi-view layer."""

    mono_model: str = ""                 # path to an .onnx (or torch) mono depth model; "" = none
    mono_provider: str = "auto"          # onnxruntime provider: cpu | cuda | auto
    mv_eta: float = 0.01                 # eta in Eq. 6 (fraction of mean depth)
    mv_min_views: int = 2                # n_c
    mv_max_depth_ratio: float = 3.0      # reject depth > ratio x median
    mv_min_parallax_deg: float = 1.0     # a view counts only with a baseline >= tan(this) x
                                         # median depth (0 = any; pure rotations confirm any depth)
    fill_small_holes: int = 0            # max hole size (px) filled when no mono model
    fill_holes_from_ba: bool = True      # no mono model: multi-view holes take the BA depth
    device: str = "auto"                 # "cpu", "cuda" or "auto" (torch part of proxy depth)
    mv_neighbors: int = 8                # other keyframes used by Eq. 6 (nearest by kf id)
    # a local BA update recomputes a keyframe's proxy depth (and that of the keyframes using
    # it as a view) only when, since it was computed, the camera moved more than this x its
    # median depth (rotation as angle x median depth) or its disparity more than this
    # (median relative change); smaller moves send the new pose with the same depth. Loop
    # closure, global BA and final updates always recompute (0 = every change recomputes)
    update_tol: float = 0.01
    upsample_disc: float = 0.1           # upsampling: a 2x2 BA cell spanning more than this
                                         # (relative disparity) is interpolated only if
                                         # continuous with its neighbours, else nearest
    upsample_guided: bool = True         # at depth edges follow the image edges (colour-guided)
    fill_plane_tol: float = 0.02         # small holes filled only if their rim is planar to this
    mono_fit_space: str = "auto"         # scale/shift fit: auto (model's output kind) | depth
                                         # (paper §3.2) | disparity
    # dense multi-view depth at processing resolution (depth/dense_depth.py): DIS flow to up
    # to dense_views neighbouring keyframes, triangulated with the BA poses (0 = off)
    dense_views: int = 0                 # off by default: docs/depth.md "Dense layer (opt-in)"
    dense_eta: float = 0.02              # views agree within this x depth (Eq. 6 per pixel)
    dense_min_views: int = 3             # >= this many agree: replaces the BA-grid depth
    dense_fill_views: int = 2            # >= this many agree: fills BA-grid holes (0 = no fill)
    dense_min_parallax_deg: float = 1.0  # a view is used at a pixel with at least this parallax


@dataclass
class MappingConfig:
    """The 3D Gaussian map (paper 3.3): rasterizer, optimisation budgets, keyframe window,
    losses, pruning / densification, learning rates and the mesh export.

    The defaults are a schedule sized for a 2-core CPU (docs/mapping.md "Defaults"); the
    paper's GPU schedule (60 / 1050 / 2000 iterations, whole window per step) is
    config/paper.yaml (``--preset paper``)."""

    device: str = "auto"                 # "auto" (CUDA when torch sees it), "cpu" or "cuda"
    # rasterizer (docs/mapping.md "Rasterizer"): auto = gsplat on CUDA when installed, else the C++
    # kernel on CPU when it builds, else pure torch (~30x slower; a warning says why); cpp /
    # torch / gsplat: exactly that one, an error when it cannot run (no silent fallback).
    # The backend that ran and why: metrics.json "map" raster_backend(_reason)
    raster_backend: str = field(default="auto", metadata={"choices": RASTER_BACKENDS})
    # Budgets (mapping/budget.py, docs/mapping.md "Budgets"): offline (lockstep replay,
    # splat-slam-run) in optimisation steps, the same whatever the load; with time_budget (live
    # input: the launcher turns it on for realtime input) wall-clock caps come on top.
    iters_per_keyframe: int = 45         # steps per keyframe, at most (paper: 60)
    iters_first: int = 300               # ... for the first keyframe (paper: 1050)
    min_iters_per_keyframe: int = 3      # steps every mapped keyframe gets, whatever the pace
    # a keyframe gets at most this x the stream seconds since the last mapped keyframe steps
    # (0 = off): the mapping follows the input's duration, not its keyframe count (fast
    # motion, many keyframes: fewer steps each); sized so that the default keeps its frames/s
    # on 2 cores
    stream_pace_steps: float = 90.0
    time_budget: bool = False            # wall-clock caps below (live input); off: steps only
    budget_s_per_keyframe: float = 4.0   # time_budget: wall seconds of one keyframe's steps (0 = none)
    budget_s_first: float = 15.0         # ... the first keyframe's
    # time_budget: budget_s_per_keyframe shrinks to this x the stream time since the last mapped kf
    stream_pace: float = 12.0
    keep_up: float = 0.0                 # time_budget, > 0: also cap a keyframe's steps at this
                                         # fraction of the stream time since the last mapped
                                         # keyframe (realtime: steps are dropped, never keyframes)
    # time_budget: while no keyframe or depth waits, the mapper goes on optimising (window +
    # random older views, a few steps at a time, new input first) for at most this many steps
    # after each mapped keyframe (0 = off); offline (step budgets) there are none
    background_steps: int = 300
    window_size: int = 8                 # keyframes in the mapping window (optimised together)
    rgb_weight: float = 0.8              # lambda in Eq. 11
    ba_depth_weight: float = 0.6         # depth-loss weight of BA-filled holes (source 3), 0..1
                                         # (docs/depth.md "Holes: BA depth at a lower weight")
    isotropy_weight: float = 1.0         # lambda_reg in Eq. 11 (paper and --preset paper: 10; 1
                                         # lets Gaussians follow edges: +0.3-0.7 dB;
                                         # docs/mapping.md "Defaults")
    downsample: int = 32                 # theta
    downsample_first: int = 16           # ... for the first keyframe (empty map)
    init_opacity: float = 0.5            # opacity of new Gaussians
    # initial scale of new Gaussians: this x the distance to their nearest seeded neighbours
    # (MonoGS/3DGS: 1). Smaller seeds overlap less: sharper from the first step, and a step
    # rasterizes fewer pixels per Gaussian (docs/mapping.md "Seeding scale")
    init_scale: float = 0.7
    kf_covisibility: float = 0.90        # k_fcov
    kf_translation: float = 0.08         # k_fm
    kf_cutoff: float = 0.3               # k_fc
    prune_every: int = 50                # (paper: 150)
    densify_every: int = 50              # (paper: 150)
    prune_opacity: float = 0.7           # remove Gaussians (old enough) below this opacity
    # final refinement steps beta, at most (the paper's 2000 in --preset paper): 1400 steps
    # take about 60 s on 2 cores (0.044 s a step on a 110-keyframe map)
    final_refine_iters: int = 1400
    final_refine_per_keyframe: int = 20  # refinement = min(beta, this x keyframes) (0 = beta)
    final_refine_s: float = 60.0         # time_budget: wall-second cap of the refinement (0 = none)
    # time_budget: the refinement ends at most this many wall seconds after the input ended
    # (the player's end of stream, or the depth stage's final digest when that came first), so
    # keyframes still queued then take the refinement's time and the map is done at a bounded
    # delay (0 = off)
    final_deadline_s: float = 0.0
    lr_means: float = 0.0016              # 10x 3DGS: +0.6 dB, -0.4 cm depth L1 on ICL (bench_mapping)
    lr_colors: float = 0.0025            # learning rate of the Gaussians' colours
    lr_opacity: float = 0.05             # ... opacities
    lr_scales: float = 0.001             # ... (log) scales
    lr_rotations: float = 0.001          # ... rotations
    lr_exposure: float = 0.01            # ... per-keyframe exposures (a, b)
    # the camera's radial vignetting V = 1 + v1 r^2 + v2 r^4 (r: distance from the principal
    # point / half the image diagonal), one for all keyframes, learned with the exposures and
    # applied with them (colour a V C + b) in the loss and the keyframe metrics
    # (docs/mapping.md "Vignetting")
    vignetting: bool = True
    lr_vignetting: float = 0.01          # learning rate of the vignetting (v1, v2)
    render_every: int = 1                # publish / save a render every N keyframes
    # views per iteration: the window (Eq. 11 sums over it; 0 = all) + random older keyframes
    window_views_per_iter: int = 3       # (paper: 0, the whole window)
    # a keyframe step (and a live background step) renders each view on a random lattice of
    # 1/n of its pixels per axis: pixel (i, j) of the render is pixel (n i + dx, n j + dy),
    # (dx, dy) drawn per view and step, filtered as the full image, so every pixel is trained
    # in turn (1 = every pixel every step; the launcher uses 2 on live input, where a step
    # costs about half; offline 2 gave -0.04 dB on fr2/desk but -0.9 dB on fr1/xyz;
    # docs/mapping.md "Lattice steps")
    step_subsample: int = 1
    # ... the newest keyframe's view of a keyframe step (0 = step_subsample); with
    # step_subsample 2, 1 here is the offline speed setting: fr2/desk, fr1/xyz, V1_02 drone
    # render -15 / -19 / -25 % time, -0.07 / -0.21 / +0.09 dB (docs/mapping.md "Lattice steps")
    step_subsample_newest: int = 0
    # ... the final refinement's steps (the launcher uses 2 on live input)
    refine_subsample: int = 1
    random_views_per_iter: int = 1       # MonoGS practice against forgetting (paper/MonoGS: 2)
    # pruning / densification (supplementary "Pruning and Densification", MonoGS / 3DGS)
    prune_recent_kfs: int = 3            # visibility pruning looks at Gaussians of the last N KFs
    prune_covis_min: int = 3             # ... and removes those seen by fewer other window KFs
    prune_min_age: int = 25              # opacity pruning spares Gaussians younger (paper: 50)
    prune_max_screen_px: float = 0.0     # remove if 2D radius exceeds this (0 = off)
    prune_max_scale_frac: float = 0.1    # remove if largest scale > frac x scene extent
    densify_grad_thresh: float = 0.0002  # mean view-space (NDC) positional gradient
    percent_dense: float = 0.01          # clone below / split above this x scene extent
    scene_extent: float = 0.0            # metres; 0 = from keyframe centres and depth
    keyframe_every: int = 0              # map_sequence only: map every k-th frame (0 = window rules)
    # revisits: a keyframe is not mapped when a mapped one is within kf_translation x median
    # depth and this many degrees of viewing direction, and a mapped keyframe that an update
    # moves onto another one's view is merged into the older (0 = off; bounds long runs in one room)
    revisit_cull_deg: float = 0.0
    # ... and, in that mode, a keyframe whose view the map already covers (this fraction of
    # its pixels rendered with accumulated opacity > 0.5) is not mapped either, whatever its
    # (drifting) pose says
    revisit_coverage: float = 0.95
    # a new keyframe seeds Gaussians only where the map does not explain it yet (rendered
    # opacity < 0.5, or rendered depth off by more than seed_depth_tol x depth): on by default
    # when a loaded map is extended (splat-slam-run --load-map RUN), so a revisited view adds none
    seed_uncovered: bool = False
    seed_depth_tol: float = 0.1          # ... relative depth difference that counts as unexplained
    # densification stops for a keyframe's Gaussians at this x the number a keyframe anchors
    # when mapped (pixels / downsample; 0 = no limit): a bounded map when views conflict
    densify_max_per_view: float = 0.0
    seed: int = 0                        # random seed of the mapper (initialisation, view picks)
    # map_mesh.ply: TSDF fusion of rendered depth + colour at the keyframe poses (mapping/mesh.py)
    mesh: bool = True                    # write map_mesh.ply with the other outputs / on save
    mesh_voxel_m: float = 0.0            # 0 = auto: 0.005 x median rendered depth (~1 cm indoors)
    mesh_trunc_voxels: float = 4.0       # TSDF truncation in voxels (reference: 0.04 m / (5/512 m))
    mesh_max_depth_m: float = 0.0        # ignore rendered depth beyond this (0 = no limit)
    mesh_min_alpha: float = 0.5          # pixels with lower accumulated opacity are not fused

    @classmethod
    def fast(cls, **overrides) -> "MappingConfig":
        """Few iterations everywhere: for tests and quick CPU looks (not for quality)."""
        base = dict(iters_per_keyframe=15, iters_first=150, final_refine_iters=30,
                    random_views_per_iter=1, window_views_per_iter=3, prune_every=50,
                    densify_every=50, prune_min_age=25, budget_s_per_keyframe=0.0,
                    budget_s_first=0.0, final_refine_per_keyframe=0, final_refine_s=0.0,
                    stream_pace=0.0, stream_pace_steps=0.0)
        base.update(overrides)
        return cls(**base)


@dataclass
class RosConfig:
    """ROS 2 frame names and input topics of the nodes."""

    map_frame: str = "map"               # fixed world frame of the map, poses and TF
    odom_frame: str = "odom"             # map -> odom: loop closure / global BA corrections
    camera_frame: str = "camera"         # odom -> camera: tracking (ROS body axes, REP-103)
    optical_frame: str = "camera_optical"  # static camera -> optical (OpenCV axes, images)
    image_topic: str = "image"           # input sensor_msgs/Image (CompressedImage: ends in /compressed)
    camera_info_topic: str = "camera_info"  # input sensor_msgs/CameraInfo topic


@dataclass
class EvaluationConfig:
    """Extra metrics of a run (metrics.json)."""

    # LPIPS of the mapped keyframes in metrics.json (``lpips``): a backbone file you supply
    # (TorchScript or torch.export, see evaluation.perceptual.lpips); "" = no LPIPS (``lpips: null``)
    lpips_backbone: str = ""
    lpips_weights: str = ""              # optional per-layer channel weights file ("" = none)


@dataclass
class SlamConfig:
    dataset: str = "default"             # label of the data set a config file is written for
    camera: CameraConfig = field(default_factory=CameraConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    depth: DepthConfig = field(default_factory=DepthConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    ros: RosConfig = field(default_factory=RosConfig)
    evaluation: EvaluationConfig = field(default_factory=EvaluationConfig)

    # ------------------------------------------------------------------ I/O
    def to_dict(self) -> Dict[str, Any]:
        return dataclasses.asdict(self)

    def flat(self) -> Dict[str, Any]:
        """Dotted names -> values (the ROS parameter names)."""
        out: Dict[str, Any] = {}

        def walk(obj, prefix):
            for f in fields(obj):
                v = getattr(obj, f.name)
                if is_dataclass(v):
                    walk(v, prefix + f.name + ".")
                else:
                    out[prefix + f.name] = list(v) if isinstance(v, tuple) else v
        walk(self, "")
        return out

    def set(self, dotted: str, value: Any) -> None:
        """Set one value by dotted name, with type checking."""
        parts = dotted.split(".")
        obj = self
        for p in parts[:-1]:
            if not hasattr(obj, p) or not is_dataclass(getattr(obj, p)):
                raise ConfigError(f"unknown config section '{p}' in '{dotted}'")
            obj = getattr(obj, p)
        _assign(obj, parts[-1], value, dotted)


def _assign(obj, name: str, value: Any, dotted: str) -> None:
    known = {f.name: f for f in fields(obj)}
    if name not in known:
        raise ConfigError(
            f"unknown config key '{dotted}'; valid keys here: {', '.join(sorted(known))}")
    current = getattr(obj, name)
    if is_dataclass(current):
        if not isinstance(value, dict):
            raise ConfigError(f"'{dotted}' must be a mapping")
        for k, v in value.items():
            _assign(current, k, v, f"{dotted}.{k}")
        return
    try:
        if isinstance(current, bool):
            if not isinstance(value, bool):
                raise TypeError
        elif isinstance(current, int):
            if isinstance(value, bool) or float(value) != int(value):
                raise TypeError
            value = int(value)
        elif isinstance(current, float):
            if isinstance(value, bool):
                raise TypeError
            value = float(value)
        elif isinstance(current, str):
            value = str(value)
        elif isinstance(current, tuple):
            value = tuple(value)
    except (TypeError, ValueError):
        raise ConfigError(
            f"'{dotted}' expects {type(current).__name__}, got {value!r}") from None
    choices = known[name].metadata.get("choices")
    if choices and value not in choices:
        raise ConfigError(f"'{dotted}' must be one of {', '.join(choices)}, got {value!r}")
    setattr(obj, name, value)


# The core: the keys a user tunes for a camera, a machine or an output (docs/configuration.md
# "Core keys"). Every other key is advanced: a method constant, a CPU budget or an ablation
# switch whose default was measured (its effect is in the reference and in docs/*.md). In a
# YAML file advanced keys go under the top-level ``advanced:`` section, nested the same way
# (``advanced: {tracking: {loop_nms: 10}}``); dotted names (``--set``, ROS parameters) are
# the same for both.
CORE_KEYS = (
    "dataset",
    "camera.width", "camera.height", "camera.max_pixels", "camera.crop", "camera.undistort",
    "camera.rolling_shutter_ms", "camera.rolling_shutter_stamp_row",
    "tracking.device", "tracking.threads", "tracking.flow_model", "tracking.motion_filter_thresh",
    "tracking.keyframe_thresh", "tracking.max_keyframe_rate", "tracking.loop_closure",
    "tracking.global_ba", "tracking.dspo",
    "depth.mono_model", "depth.device",
    "mapping.device", "mapping.raster_backend", "mapping.iters_per_keyframe",
    "mapping.iters_first", "mapping.final_refine_iters", "mapping.time_budget",
    "mapping.window_size", "mapping.vignetting", "mapping.mesh", "mapping.seed",
    "mapping.revisit_cull_deg",
    "ros.map_frame", "ros.odom_frame", "ros.camera_frame", "ros.optical_frame",
    "ros.image_topic", "ros.camera_info_topic",
    "evaluation.lpips_backbone", "evaluation.lpips_weights",
)
ADVANCED = "advanced"                # the YAML section holding every key not in CORE_KEYS


def is_core(dotted: str) -> bool:
    """Whether ``dotted`` (``section.key``) is one of the core keys a user tunes."""
    return dotted in CORE_KEYS


def _apply_advanced(cfg: SlamConfig, value: Any, where: str) -> None:
    """The ``advanced:`` section of a YAML file: {section: {key: value}} of advanced keys."""
    if not isinstance(value, dict):
        raise ConfigError(f"{where}: '{ADVANCED}' must be a mapping of sections")
    for sec, keys in value.items():
        if not isinstance(keys, dict):
            raise ConfigError(f"{where}: '{ADVANCED}.{sec}' must be a mapping of keys")
        for k, v in keys.items():
            dotted = f"{sec}.{k}"
            if is_core(dotted):
                raise ConfigError(f"{where}: '{dotted}' is a core key: write it under "
                                  f"'{sec}:', not under '{ADVANCED}:'")
            cfg.set(dotted, v)


def _apply_yaml(cfg: SlamConfig, p: Path) -> None:
    if not p.is_file():
        raise ConfigError(f"config file not found: {p}")
    try:
        data = yaml.safe_load(p.read_text()) or {}
    except yaml.YAMLError as e:
        raise ConfigError(f"config file {p} is not valid YAML: {e}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"config file {p} must hold a mapping at the top level")
    for k, v in data.items():
        if k == "dataset":
            cfg.dataset = str(v)
            continue
        if k == ADVANCED:
            _apply_advanced(cfg, v, str(p))
            continue
        _assign(cfg, k, v, k)


def preset_path(name: str) -> Path:
    """``--preset NAME`` -> the shipped ``config/NAME.yaml`` (ConfigError naming the presets)."""
    name = str(name).strip()
    p = config_dir() / f"{name}.yaml"
    if not name or "/" in name or not p.is_file():
        names = sorted(f.stem for f in config_dir().glob("*.yaml"))
        raise ConfigError(f"unknown preset {name!r}; shipped presets: {', '.join(names)}")
    return p


def load_config(path: Optional[str | Path] = None,
                overrides: Optional[Dict[str, Any]] = None,
                preset: Optional[str] = None) -> SlamConfig:
    """Defaults, then the preset (config/NAME.yaml), then the YAML file (if any), then dotted
    overrides."""
    cfg = SlamConfig()
    if preset:
        _apply_yaml(cfg, preset_path(preset))
    if path is not None:
        _apply_yaml(cfg, Path(path))
    for k, v in (overrides or {}).items():
        cfg.set(k, v)
    return cfg


def dump_config(cfg: SlamConfig, path: str | Path, header: str = "") -> Path:
    """Write ``cfg`` as a YAML file that :func:`load_config` reads back to an equal config:
    the core keys under their sections, every other key under ``advanced:``; ``header``
    (comment lines) first."""
    core: Dict[str, Any] = {}
    advanced: Dict[str, Any] = {}
    for dotted, v in cfg.flat().items():
        if "." not in dotted:
            core[dotted] = v
            continue
        sec, key = dotted.split(".", 1)
        (core if is_core(dotted) else advanced).setdefault(sec, {})[key] = v
    p = Path(path)
    p.write_text(header + yaml.safe_dump({**core, ADVANCED: advanced}, sort_keys=False))
    return p


def config_dir() -> Path:
    """The shipped config/ folder (repository checkout or installed share)."""
    here = Path(__file__).resolve().parent.parent / "config"
    if here.is_dir():
        return here
    import sys
    installed = Path(sys.prefix) / "share" / "splat_slam_ros" / "config"
    return installed if installed.is_dir() else here
