#!/usr/bin/env python
"""Rasterizer speed: C++ kernel vs the pure-torch reference on room-like scenes.

Prints a table and writes benchmarks/results/rasterizer.json. Scenes: Gaussians initialised
like the mapper does from a keyframe (pixels unprojected onto the surfaces of a box room with
a table-sized box, flattened along the surface normal, sized to the pixel spacing), plus 23 %
extra Gaussians from nearby "other keyframes" so several layers overlap along each ray; the
"map" scene adds 9x as many Gaussians out of view (the rest of a larger map, behind the
camera), where the per-view cost should follow the Gaussians in view, not the map's size.

    python benchmarks/bench_rasterizer.py [--threads 2] [--repeats 5] [--quick] [--also-jemalloc]

Times are wall-clock medians (ms) and, in brackets, the CPU time of all threads; the load
average is recorded because other processes on the machine slow both down.

The forward+backward loss is L1 on rgb + 0.1 * L1 on depth (as in mapping).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

from splat_slam_ros.geometry import matrix_to_quat
from splat_slam_ros.mapping.rasterizer import rasterize
from splat_slam_ros.mapping.rasterizer.kernel import load_extension

JEMALLOC = ("/usr/lib/x86_64-linux-gnu/libjemalloc.so.2", "/usr/lib/aarch64-linux-gnu/libjemalloc.so.2")


def room_scene(n: int, width: int, height: int, seed: int = 0):
    """N Gaussians on the surfaces of a 4 x 2.7 x 5 m room seen from inside."""
    g = torch.Generator().manual_seed(seed)
    fx = fy = 0.9 * width
    cx, cy = (width - 1) / 2, (height - 1) / 2
    n_main = int(n * 0.77)

    def ray_cast(u, v):
        d = torch.stack([(u - cx) / fx, (v - cy) / fy, torch.ones_like(u)], -1)
        # planes: x = +-2, y = -1.2 (ceiling) / 1.5 (floor), z = 5 (back wall), box at z 2..2.8
        cands, normals = [], []
        for axis, off in ((0, -2.0), (0, 2.0), (1, -1.2), (1, 1.5), (2, 5.0)):
            t = off / d[:, axis]
            t = torch.where(t > 0, t, torch.full_like(t, math.inf))
            cands.append(t)
            nrm = torch.zeros(3)
            nrm[axis] = 1.0
            normals.append(nrm.expand_as(d))
        # a table-sized box in front: its front face z = 2.2, x in [-0.8, 0.6], y in [0.5, 1.5]
        t = 2.2 / d[:, 2]
        p = d * t[:, None]
        hit = (p[:, 0] > -0.8) & (p[:, 0] < 0.6) & (p[:, 1] > 0.5)
        cands.append(torch.where(hit, t, torch.full_like(t, math.inf)))
        normals.append(torch.tensor([0.0, 0.0, 1.0]).expand_as(d))
        T = torch.stack(cands, -1)
        t_min, idx = T.min(-1)
        nrm = torch.stack(normals, 1)[torch.arange(len(u)), idx]
        return d * t_min[:, None], nrm

    u = torch.rand(n, generator=g) * width - 0.5
    v = torch.rand(n, generator=g) * height - 0.5
    pts, nrm = ray_cast(u, v)
    # extra Gaussians "from other keyframes": shifted along the surface, slightly off it
    extra = torch.arange(n) >= n_main
    pts = pts + extra[:, None] * (torch.randn(n, 3, generator=g) * 0.05)
    spacing_px = math.sqrt(width * height / n_main)
    z = pts[:, 2]
    s_tan = spacing_px * z / fx * (0.6 + 0.8 * torch.rand(n, generator=g))
    s_nrm = s_tan * 0.1
    # orthonormal frame with the normal as third axis
    a = torch.where(nrm[:, :1].abs() > 0.9, torch.tensor([0.0, 1.0, 0.0]), torch.tensor([1.0, 0.0, 0.0]))
    t1 = torch.nn.functional.normalize(torch.cross(nrm, a, dim=-1), dim=-1)
    t2 = torch.cross(nrm, t1, dim=-1)
    Rm = torch.stack([t1, t2, nrm], -1)
    quats = matrix_to_quat(Rm.double()).float()
    scales = torch.stack([s_tan, s_tan * (0.5 + torch.rand(n, generator=g)), s_nrm], -1)
    opac = 0.5 + 0.49 * torch.rand(n, generator=g)
    colors = torch.rand(n, 3, generator=g)
    viewmat = torch.eye(4)
    return (pts.float().contiguous(), quats.contiguous(), scales.float().contiguous(),
            opac.contiguous(), colors.contiguous(), viewmat, (fx, fy, cx, cy))


def with_out_of_view(scene, n_out: int, seed: int = 1):
    """The scene plus ``n_out`` Gaussians of the rest of a map: behind the camera (culled by
    the projection, as most of a large map is from any one keyframe)."""
    means, quats, scales, opac, colors, viewmat, intr = scene
    g = torch.Generator().manual_seed(seed)
    far = torch.rand(n_out, 3, generator=g) * torch.tensor([8.0, 3.0, 6.0]) - torch.tensor([4.0, 1.5, 7.0])
    pick = torch.randint(0, len(means), (n_out,), generator=g)
    return (torch.cat([means, far]).contiguous(), torch.cat([quats, quats[pick]]).contiguous(),
            torch.cat([scales, scales[pick]]).contiguous(), torch.cat([opac, opac[pick]]).contiguous(),
            torch.cat([colors, colors[pick]]).contiguous(), viewmat, intr)


def time_backend(scene, width, height, backend, repeats):
    means, quats, scales, opac, colors, viewmat, intr = scene
    params = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, colors)]
    target = torch.rand(height, width, 3, generator=torch.Generator().manual_seed(1))

    def fwd():
        with torch.no_grad():
            rasterize(*params, viewmat, intr, width, height, backend=backend)

    def fwd_bwd():
        out = rasterize(*params, viewmat, intr, width, height, backend=backend)
        loss = (out.rgb - target).abs().mean() + 0.1 * (out.depth - 2.0).abs().mean()
        loss.backward()
        for p in params:
            p.grad = None

    res = {}
    for name, fn in (("forward_ms", fwd), ("forward_backward_ms", fwd_bwd)):
        fn()  # warm-up
        ts, cpu = [], []
        for _ in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            fn()
            ts.append((time.perf_counter() - t0) * 1e3)
            cpu.append((time.process_time() - c0) * 1e3)
        res[name] = statistics.median(ts)
        res[name + "_min"] = min(ts)
        res[name + "_cpu"] = statistics.median(cpu)  # CPU time of all threads
    with torch.no_grad():
        out = rasterize(*params, viewmat, intr, width, height, backend=backend)
    res["visible"] = int(out.visible.sum())
    res["mean_alpha"] = float(out.alpha.mean())
    return res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="only 20k @ 320x240")
    ap.add_argument("--no-reference", action="store_true", help="skip the pure-torch reference")
    ap.add_argument("--also-jemalloc", action="store_true",
                    help="afterwards run again in a subprocess with LD_PRELOAD=libjemalloc.so.2")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results" / "rasterizer.json"))
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    load_extension()
    # (Gaussians in view, width, height, Gaussians out of view)
    configs = [(20000, 320, 240, 0)] + ([] if args.quick else
                                        [(20000, 320, 240, 180000), (100000, 640, 480, 0)])
    preload = os.environ.get("LD_PRELOAD", "")
    allocator = "jemalloc" if "jemalloc" in preload else "glibc"
    try:
        load = os.getloadavg()
    except OSError:
        load = None
    policy = os.environ.get("OMP_WAIT_POLICY", "default").lower()
    results = {"threads": args.threads, "allocator": allocator, "omp_wait_policy": policy,
               "torch": torch.__version__,
               "cpu": platform.processor() or platform.machine(),
               "cpu_capability": torch.backends.cpu.get_cpu_capability(),
               "loadavg_before": load, "configs": []}
    print(f"threads={args.threads} allocator={allocator} OMP_WAIT_POLICY={policy} loadavg={load}")
    print(f"{'scene':>18} {'backend':>7} {'fwd ms':>9} {'fwd+bwd ms':>11} {'(cpu ms)':>9} {'visible':>8}")
    for n, w, h, n_out in configs:
        scene = room_scene(n, w, h)
        if n_out:
            scene = with_out_of_view(scene, n_out)
        entry = {"gaussians": n + n_out, "in_view": n, "width": w, "height": h}
        label = f"{n // 1000}k" + (f" of {(n + n_out) // 1000}k" if n_out else "")
        backends = ["cpp"] + ([] if args.no_reference or n_out else ["torch"])
        for be in backends:
            r = time_backend(scene, w, h, be, args.repeats if be == "cpp" else max(1, args.repeats // 2))
            entry[be] = r
            print(f"{f'{label} @ {w}x{h}':>18} {be:>7} {r['forward_ms']:9.1f} "
                  f"{r['forward_backward_ms']:11.1f} {r['forward_backward_ms_cpu']:9.1f} "
                  f"{r['visible']:8d}")
        if "torch" in entry:
            entry["speedup_forward"] = entry["torch"]["forward_ms"] / entry["cpp"]["forward_ms"]
            entry["speedup_forward_backward"] = (entry["torch"]["forward_backward_ms"]
                                                 / entry["cpp"]["forward_backward_ms"])
            print(f"{'':>18} speed-up  {entry['speedup_forward']:8.1f}x "
                  f"{entry['speedup_forward_backward']:10.1f}x")
        results["configs"].append(entry)
    try:
        results["loadavg_after"] = os.getloadavg()
    except OSError:
        pass
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    # keep results of other allocators/thread counts side by side
    old = json.loads(out.read_text()) if out.is_file() else {}
    if not isinstance(old, dict) or "runs" not in old:
        old = {"runs": {}}
    old["runs"][f"{allocator}_t{args.threads}_omp-{policy}"] = results
    out.write_text(json.dumps(old, indent=2))
    print(f"wrote {out}")
    if args.also_jemalloc and allocator != "jemalloc":
        lib = next((p for p in JEMALLOC if Path(p).is_file()), None)
        if lib is None:
            print("jemalloc not found (apt-get install libjemalloc2); skipped")
            return 0
        env = dict(os.environ, LD_PRELOAD=lib, MALLOC_CONF="dirty_decay_ms:-1,muzzy_decay_ms:-1")
        argv2 = [a for a in (argv if argv is not None else sys.argv[1:]) if a != "--also-jemalloc"]
        return subprocess.call([sys.executable, __file__, *argv2], env=env)
    return 0


if __name__ == "__main__":
    sys.exit(main())
