"""Gaussian map export/import in the standard 3D Gaussian Splatting PLY layout.

Binary little-endian, one ``vertex`` element with float properties
``x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 opacity scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3``
(what the 3DGS reference code writes for SH degree 0 and what splat viewers read):

- ``f_dc_k`` is the SH DC coefficient: colour = 0.5 + C0 * f_dc with C0 = 0.28209479177387814;
- ``opacity`` is the logit, ``scale_k`` the log-scale;
- ``rot_0..3`` is the quaternion in (w, x, y, z) order (we store x, y, z, w internally).

We add one extra ``int kf_id`` property (the anchoring keyframe); viewers ignore it.
"""
from __future__ import annotations

from pathlib import Path
from typing import Dict, Optional

import numpy as np

SH_C0 = 0.28209479177387814
FLOAT_PROPS = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"]
               + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)])

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


class PlyError(ValueError):
    """A PLY file that is not a readable Gaussian splat file."""


def save_gaussians_ply(path, means, quats_xyzw, log_scales, opacity_logits, colors,
                       kf_id: Optional[np.ndarray] = None) -> None:
    """Write Gaussians (numpy or torch arrays) as a binary little-endian 3DGS PLY."""
    def a(x):
        x = x.detach().cpu().numpy() if hasattr(x, "detach") else np.asarray(x)
        return x.astype(np.float32)
    means, q, ls, op, col = a(means), a(quats_xyzw), a(log_scales), a(opacity_logits), a(colors)
    n = len(means)
    dtype = [(p, "<f4") for p in FLOAT_PROPS]
    if kf_id is not None:
        dtype.append(("kf_id", "<i4"))
    v = np.zeros(n, dtype=dtype)
    v["x"], v["y"], v["z"] = means[:, 0], means[:, 1], means[:, 2]
    f_dc = (col.reshape(n, 3) - 0.5) / SH_C0
    for i in range(3):
        v[f"f_dc_{i}"] = f_dc[:, i]
        v[f"scale_{i}"] = ls.reshape(n, 3)[:, i]
    v["opacity"] = op.reshape(n)
    q = q.reshape(n, 4)
    v["rot_0"], v["rot_1"], v["rot_2"], v["rot_3"] = q[:, 3], q[:, 0], q[:, 1], q[:, 2]
    if kf_id is not None:
        k = kf_id.detach().cpu().numpy() if hasattr(kf_id, "detach") else np.asarray(kf_id)
        v["kf_id"] = k.astype(np.int32)
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    for name, t in dtype:
        header.append(f"property {'int' if t == '<i4' else 'float'} {name}")
    header.append("end_header")
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    with open(p, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(v.tobytes())


def load_gaussians_ply(path) -> Dict[str, np.ndarray]:
    """Read a 3DGS PLY (ours or another tool's). Returns float32 arrays
    means (N,3), quats (N,4) x y z w, log_scales (N,3), opacity_logits (N,), colors (N,3)
    and kf_id (N,) int64 (zeros when the file has none). Higher SH bands are ignored."""
    p = Path(path)
    if not p.is_file():
        raise PlyError(f"PLY file not found: {p}")
    with open(p, "rb") as f:
        if f.readline().strip() != b"ply":
            raise PlyError(f"{p} is not a PLY file")
        fmt, n, props, in_vertex = None, None, [], False
        while True:
            line = f.readline()
            if not line:
                raise PlyError(f"{p}: header has no end_header")
            tok = line.decode("ascii", "replace").split()
            if not tok or tok[0] in ("comment", "obj_info"):
                continue
            if tok[0] == "end_header":
                break
            if tok[0] == "format":
                fmt = tok[1]
            elif tok[0] == "element":
                in_vertex = tok[1] == "vertex"
                if in_vertex:
                    n = int(tok[2])
                elif n is None:
                    raise PlyError(f"{p}: element '{tok[1]}' before 'vertex' is not supported")
            elif tok[0] == "property" and in_vertex:
                if tok[1] == "list":
                    raise PlyError(f"{p}: list properties in 'vertex' are not supported")
                if tok[1] not in _PLY_TYPES:
                    raise PlyError(f"{p}: unknown PLY type '{tok[1]}'")
                props.append((tok[2], _PLY_TYPES[tok[1]]))
        if fmt not in ("binary_little_endian", "binary_big_endian"):
            raise PlyError(f"{p}: only binary PLY files are supported (found '{fmt}')")
        if n is None:
            raise PlyError(f"{p}: no 'vertex' element")
        order = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([(name, order + t) for name, t in props])
        buf = f.read(dtype.itemsize * n)
        if len(buf) < dtype.itemsize * n:
            raise PlyError(f"{p}: file is truncated ({len(buf)} of {dtype.itemsize * n} bytes)")
        v = np.frombuffer(buf, dtype=dtype, count=n)
    names = set(v.dtype.names)
    need = {"x", "y", "z", "opacity", "scale_0", "scale_1", "scale_2",
            "rot_0", "rot_1", "rot_2", "rot_3"}
    if not need <= names:
        raise PlyError(f"{p} is not a Gaussian splat PLY (missing {sorted(need - names)})")
    col = lambda *k: np.stack([v[x].astype(np.float32) for x in k], 1)  # noqa: E731
    if {"f_dc_0", "f_dc_1", "f_dc_2"} <= names:
        colors = 0.5 + SH_C0 * col("f_dc_0", "f_dc_1", "f_dc_2")
    elif {"red", "green", "blue"} <= names:
        colors = col("red", "green", "blue") / 255.0
    else:
        raise PlyError(f"{p} has no colour (f_dc_0..2 or red/green/blue)")
    q_wxyz = col("rot_0", "rot_1", "rot_2", "rot_3")
    return {
        "means": col("x", "y", "z"),
        "quats": np.ascontiguousarray(q_wxyz[:, [1, 2, 3, 0]]),
        "log_scales": col("scale_0", "scale_1", "scale_2"),
        "opacity_logits": v["opacity"].astype(np.float32),
        "colors": colors.astype(np.float32),
        "kf_id": (v["kf_id"].astype(np.int64) if "kf_id" in names
                  else np.zeros(n, dtype=np.int64)),
    }
