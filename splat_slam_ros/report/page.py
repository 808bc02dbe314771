"""The run report page: one self-contained HTML file (images embedded, no script, no date).

Sections (element ids, in order): ``summary``, ``warnings``, ``missing``, ``trajectory``,
``keyframes``, ``map``, ``timing``, ``config``. Each is always present; one without data
says what is missing and why.
"""
from __future__ import annotations

import html
from typing import Dict, List, Sequence

import numpy as np

from splat_slam_ros.report import plots as rp
from splat_slam_ros.report.recording import keyframe_rate_text
from splat_slam_ros.report.run_record import (TILE_NAMES, THUMB_WIDTH, RunRecord, data_uri,
                                              depth_unit, fmt, headline, keyframe_positions,
                                              keyframe_tiles, stage_times,
                                              worst_keyframe)

CSS = """
body{font-family:system-ui,sans-serif;margin:1.5em;color:#222;max-width:1500px}
h1{font-size:1.4em}h2{font-size:1.15em;border-bottom:1px solid #ccc;padding-bottom:.2em}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ddd;padding:3px 7px;
text-align:right;font-size:.9em}th{background:#f4f4f4}td.l,th.l{text-align:left}
img{max-width:100%}.kf img{width:220px;display:block}.poor td{background:#fde8e8}
.missing{color:#8a5a00}.warn li{color:#a01010}pre{background:#f7f7f7;padding:.7em;
font-size:.8em;max-height:40em;overflow:auto}.note{color:#555;font-size:.9em}
"""


def _e(s) -> str:
    return html.escape(str(s), quote=True)


def _img(png: bytes, alt: str, cls: str = "") -> str:
    c = f' class="{cls}"' if cls else ""
    return f'<img src="{data_uri(png)}" alt="{_e(alt)}"{c}>'


def _table(rows: Sequence[Sequence[str]], head: Sequence[str] = ()) -> str:
    out = ["<table>"]
    if head:
        out.append("<tr>" + "".join(f'<th class="l">{_e(h)}</th>' if i == 0 else
                                    f"<th>{_e(h)}</th>" for i, h in enumerate(head)) + "</tr>")
    for r in rows:
        out.append("<tr>" + "".join(f'<td class="l">{c}</td>' if i == 0 else f"<td>{c}</td>"
                                    for i, c in enumerate(r)) + "</tr>")
    return "\n".join(out + ["</table>"])


def _missing(text: str) -> str:
    return f'<p class="missing">{_e(text)}</p>'


# ---------------------------------------------------------------------- sections
def _summary(rec: RunRecord, png: bytes) -> str:
    m = rec.metrics
    rows = [("dataset", _e(rec.name)), ("mode", _e(m.get("mode", "n/a"))),
            ("frames", fmt(m.get("frames"))), ("keyframes", fmt(m.get("keyframes"))),
            ("wall time", fmt(m.get("wall_s"), 1, "s")), ("frames/s", fmt(m.get("fps"), 2))]
    kf_rate = keyframe_rate_text(m)
    if kf_rate is not None:
        rows.insert(4, ("keyframes per second of input", _e(kf_rate)))
    if rec.ate is not None:
        rows.append(("ATE RMSE, all frames (Sim(3))", fmt(rec.ate["rmse_cm"], 2, "cm")))
    if rec.ate_kf is not None:
        rows.append(("ATE RMSE, keyframes (Sim(3))", fmt(rec.ate_kf["rmse_cm"], 2, "cm")))
    for k, label, nd, unit in (("psnr", "keyframe PSNR", 2, "dB"), ("ssim", "keyframe SSIM", 3, ""),
                               ("depth_l1_cm", "depth L1 (ground truth)", 2, "cm"),
                               ("gaussians", "Gaussians", 0, ""), ("map_mb", "map size", 2, "MB")):
        if k in m:
            rows.append((label, fmt(m[k], nd, unit)))
    return (f'<section id="summary"><h2>Summary</h2>\n<p>{_e(headline(rec))}</p>\n'
            + _table(rows) + "\n" + _img(png, "summary figure (report.png)") + "</section>")


def _warnings(rec: RunRecord) -> str:
    body = ('<ul class="warn">' + "".join(f"<li>{_e(w)}</li>" for w in rec.warnings) + "</ul>"
            if rec.warnings else "<p>none: the run recorded no warning.</p>")
    return f'<section id="warnings"><h2>Warnings</h2>\n{body}</section>'


def _missing_section(rec: RunRecord) -> str:
    body = ("".join(_missing(t) for t in rec.missing) if rec.missing
            else "<p>nothing: every part of the report has data.</p>")
    return f'<section id="missing"><h2>Missing from this run</h2>\n{body}</section>'


def _trajectory_png(rec: RunRecord) -> bytes:
    fig, ax = rp.new_figure(13, 5, 1, 2)
    kf = keyframe_positions(rec)
    if rec.ate is not None:
        rp.draw_trajectory(ax[0], rec.ate["aligned_est_poses"][:, :3, 3],
                           rec.ate["gt_poses"][:, :3, 3], kf, "estimate over ground truth")
        rp.draw_error(ax[1], rec.ate["timestamps"], rec.ate["errors_cm"], rec.ate["rmse_cm"], "")
    else:
        est = rec.est[1][:, :3, 3] if rec.est is not None else None
        rp.draw_trajectory(ax[0], est, None, kf, "estimate (no ground truth)")
        rp.draw_error(ax[1], None, None, None, "no ground truth: no trajectory error")
    fig.tight_layout()
    return rp.fig_png(fig)


def _trajectory(rec: RunRecord) -> str:
    parts = ['<section id="trajectory"><h2>Trajectory</h2>']
    if rec.est is None and rec.est_kf is None:
        parts.append(_missing("no estimated trajectory (trajectory_full.txt missing or empty)"))
        return "\n".join(parts + ["</section>"])
    if rec.ate is not None:
        rows = []
        for label, a in (("all frames", rec.ate), ("keyframes", rec.ate_kf)):
            if a is not None:
                rows.append((label, fmt(a["rmse_cm"], 3), fmt(a["mean_cm"], 3),
                             fmt(a["median_cm"], 3), fmt(a["max_cm"], 3),
                             fmt(a["n_matched"]), fmt(a["scale"], 4)))
        parts.append(_table(rows, ("poses", "ATE RMSE [cm]", "mean", "median", "max",
                                   "matched", "Sim(3) scale")))
        parts.append('<p class="note">Estimate aligned to the ground truth with Umeyama '
                     '(Sim(3), all matched poses), as splat-slam-eval does.</p>')
    else:
        parts += [_missing(t) for t in rec.missing if t.startswith(("ground truth", "trajectory"))]
    parts.append(_img(_trajectory_png(rec), "trajectory and error over time"))
    return "\n".join(parts + ["</section>"])


def _pick(kfs: List[dict], n: int) -> List[dict]:
    """At most n keyframes, evenly spread, always with the lowest-PSNR one."""
    if len(kfs) <= n:
        return kfs
    idx = set(int(i) for i in np.linspace(0, len(kfs) - 1, n).round())
    worst = min(range(len(kfs)), key=lambda i: (kfs[i].get("psnr", 1e9), i))
    if worst not in idx:                        # it replaces the nearest one picked
        idx.discard(min(idx, key=lambda i: (abs(i - worst), i)))
        idx.add(worst)
    return [kfs[i] for i in sorted(idx)]


def _keyframe_row(rec: RunRecord, k: dict, factor: float, poor: bool) -> str:
    tiles = keyframe_tiles(rec, int(k["kf_id"]))
    cells = []
    for t, name in zip(tiles, TILE_NAMES):
        cells.append(_img(rp.jpeg_bytes(rp.thumbnail(t, THUMB_WIDTH)), f"kf {k['kf_id']} {name}")
                     if t is not None else '<span class="missing">not recorded</span>')
    l1 = k.get("depth_l1_proxy")
    stats = [f"PSNR {fmt(k.get('psnr'), 2, 'dB')}", f"SSIM {fmt(k.get('ssim'), 3)}",
             f"depth L1 vs proxy {fmt(None if l1 is None else l1 * factor, 2)}",
             f"coverage {fmt(100 * k.get('coverage', float('nan')), 1, '%')}",
             f"proxy depth {fmt(100 * k.get('proxy_valid', float('nan')), 1, '%')}"]
    if "depth_l1_cm" in k:
        stats.insert(3, f"depth L1 vs ground truth {fmt(k['depth_l1_cm'], 2, 'cm')}")
    head = f"<b>{k['kf_id']}</b><br>t={fmt(k.get('timestamp'), 3)}<br>" + "<br>".join(stats)
    cls = ' class="poor"' if poor else ""
    return f'<tr{cls}><td class="l">{head}</td>' + "".join(
        f'<td class="kf">{c}</td>' for c in cells) + "</tr>"


def _keyframes(rec: RunRecord, max_keyframes: int) -> str:
    parts = ['<section id="keyframes"><h2>Keyframes</h2>']
    kfs = rec.keyframes
    if not kfs:
        parts.append(_missing("no map: no rendered keyframes (see 'Missing from this run')"))
        return "\n".join(parts + ["</section>"])
    factor, unit = depth_unit(rec)
    shown = _pick(kfs, max_keyframes)
    w = worst_keyframe(rec)
    parts.append(f'<p class="note">{len(shown)} of {len(kfs)} mapped keyframes. Rendered RGB '
                 f"uses the keyframe's learned exposure; depth colours (turbo, near = blue) share "
                 f"one range per keyframe, grey = no depth; colour error = mean |render - input| "
                 f"over RGB, black 0 to yellow {rp.ERROR_RANGE:.2f}; depth L1 in {_e(unit)}; "
                 f"coverage = pixels the map renders; the lowest-PSNR keyframe is "
                 f"highlighted.</p>")
    head = ["keyframe"] + list(TILE_NAMES)
    rows = ["<table>", "<tr>" + "".join(f"<th>{_e(h)}</th>" for h in head) + "</tr>"]
    rows += [_keyframe_row(rec, k, factor, w is not None and k["kf_id"] == w["kf_id"])
             for k in shown]
    parts.append("\n".join(rows + ["</table>"]))
    return "\n".join(parts + ["</section>"])


def _map(rec: RunRecord) -> str:
    parts = ['<section id="map"><h2>Map</h2>']
    st: Dict = dict((rec.kf_doc or {}).get("map") or rec.metrics.get("map") or {})
    hist = rec.history
    if not st and not hist:
        parts.append(_missing("no map: no map size or history recorded"))
        return "\n".join(parts + ["</section>"])
    if hist:
        fig, ax = rp.new_figure(8, 3.6)
        rp.draw_map_size(ax, hist, "")
        fig.tight_layout()
        parts.append(_img(rp.fig_png(fig), "map size over the run"))
        ms = np.array([h["ms"] for h in hist if h.get("mapped")], dtype=np.float64)
        if len(ms):
            parts.append(f'<p class="note">{len(hist)} keyframes offered to the mapper, '
                         f"{len(ms)} mapped; mapping time per mapped keyframe: mean "
                         f"{ms.mean() / 1000:.2f} s, max {ms.max() / 1000:.2f} s.</p>")
    else:
        parts.append(_missing("map history not recorded (a mapper restarted from its "
                              "snapshot, or a run made before the report existed)"))
    keys = ("gaussians", "keyframes", "map_mb", "iterations", "deformations",
            "deformed_gaussians", "cloned", "split", "pruned_opacity", "pruned_size",
            "pruned_visibility")
    rows = [(k.replace("_", " "), fmt(st[k], 3)) for k in keys if k in st]
    if rows:
        parts.append("<p>Final map:</p>" + _table(rows))
    return "\n".join(parts + ["</section>"])


def _timing(rec: RunRecord) -> str:
    parts = ['<section id="timing"><h2>Time</h2>']
    m = rec.metrics
    stages, unit = stage_times(rec)
    if not stages:
        parts.append(_missing("no timings recorded (metrics.json missing or without timings)"))
        return "\n".join(parts + ["</section>"])
    wall = m.get("wall_s")
    share = (lambda v: fmt(100 * v / wall, 1, "%")) if isinstance(wall, (int, float)) and wall > 0 \
        else (lambda v: "n/a")
    if m.get("timings_s"):
        rows = [(_e(k), fmt(v, 2), share(v)) for k, v in stages.items()]
        parts.append(_table(rows, ("stage", "wall time [s]", "share of the run")))
    else:
        nodes = m.get("nodes") or {}
        rows = [(_e(k), fmt(v.get("cpu_s"), 2), fmt(v.get("peak_rss_mb"), 0, "MB"),
                 fmt(v.get("restarts"))) for k, v in nodes.items()]
        parts.append(_table(rows, ("node", "CPU time [s]", "peak RSS", "restarts")))
        extra = [(label, fmt(m.get(k), 1, "s")) for k, label in
                 (("wall_total_s", "wall time including start-up and saving"),
                  ("refine_s", "final map refinement (mapper, after the last frame)"))
                 if isinstance(m.get(k), (int, float))]
        if extra:
            parts.append(_table(extra))
    parts.append(f"<p>{fmt(m.get('frames'))} frames in {fmt(wall, 1, 's')}: "
                 f"<b>{fmt(m.get('fps'), 2)} frames/s</b>.</p>")
    fig, ax = rp.new_figure(7, 0.6 + 0.35 * len(stages))
    rp.draw_timings(ax, stages, unit, "")
    fig.tight_layout()
    parts.append(_img(rp.fig_png(fig), "time per stage"))
    return "\n".join(parts + ["</section>"])


def _config(rec: RunRecord) -> str:
    body = (f"<pre>{_e(rec.config_text)}</pre>" if rec.config_text is not None
            else _missing("the configuration of this run was not recorded (no config.yaml)"))
    return f'<section id="config"><h2>Configuration</h2>\n{body}</section>'


def build_html(rec: RunRecord, summary_png: bytes, max_keyframes: int = 40) -> str:
    """The whole page for one run (deterministic: same files, same bytes)."""
    title = f"Splat-SLAM run report: {rec.name}"
    body = [_summary(rec, summary_png), _warnings(rec), _missing_section(rec), _trajectory(rec),
            _keyframes(rec, max_keyframes), _map(rec), _timing(rec), _config(rec)]
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\n"
            f"<title>{_e(title)}</title>\n<style>{CSS}</style></head>\n<body>\n"
            f"<h1>{_e(title)}</h1>\n" + "\n".join(body) + "\n</body></html>\n")
