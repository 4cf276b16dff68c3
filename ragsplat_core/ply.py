"""Trained Gaussians <-> the standard 3DGS PLY that splat viewers (SuperSplat, the 3DGS SIBR viewer, gsplat
viewers, nerfstudio) open.

One `vertex` element, binary little-endian float32 properties in this order: x y z nx ny nz f_dc_0..2
f_rest_0..(3(K-1)-1) opacity scale_0..2 rot_0..3, where f_rest is channel-major (all R coefficients,
then G, then B), opacity is the logit, scales are logs and rot is the (w, x, y, z) quaternion, exactly as
3DGS's `save_ply` writes them. Normals are zero (3DGS writes zeros too).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from ragsplat.outputs import atomic_path


def _columns(num_rest: int) -> list[str]:
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(num_rest)] + ["opacity", "scale_0", "scale_1", "scale_2"]
            + ["rot_0", "rot_1", "rot_2", "rot_3"])


def save_ply(path: str | Path, splats) -> Path:
    """Write `splats` (ParameterDict or dict of tensors, layout of `gaussians.py`) as a 3DGS PLY."""
    path = Path(path)
    means = splats["means"].detach().cpu().float()
    n = means.shape[0]
    rest = splats["shN"].detach().cpu().float() if "shN" in splats else torch.zeros(n, 0, 3)
    data = torch.cat([
        means, torch.zeros(n, 3),
        splats["sh0"].detach().cpu().float().reshape(n, 3),
        rest.transpose(1, 2).reshape(n, -1),  # [N, 3*(K-1)] channel-major
        splats["opacities"].detach().cpu().float().reshape(n, 1),
        splats["scales"].detach().cpu().float(),
        splats["quats"].detach().cpu().float(),
    ], 1).numpy().astype("<f4")
    cols = _columns(rest.shape[1] * 3)
    header = "ply\nformat binary_little_endian 1.0\n" + f"element vertex {n}\n"
    header += "".join(f"property float {c}\n" for c in cols) + "end_header\n"
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(np.ascontiguousarray(data).tobytes())
    return path


def load_ply(path: str | Path) -> dict[str, torch.Tensor]:
    """Read a 3DGS PLY (binary little-endian, float properties) back into tensors (float32, CPU).

    Raises ValueError (one line) for anything else.
    """
    path = Path(path)
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise ValueError(f"{path}: not a PLY file")
        props, count, fmt = [], None, None
        while True:
            line = f.readline()
            if not line:
                raise ValueError(f"{path}: PLY header has no end_header")
            words = line.decode("ascii", "replace").split()
            if not words:
                continue
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                if words[1] != "vertex" or count is not None:
                    raise ValueError(f"{path}: expected a single 'vertex' element, got {words[1]!r}")
                count = int(words[2])
            elif words[0] == "property":
                if words[1] != "float":
                    raise ValueError(f"{path}: property {words[-1]} is {words[1]}, expected float")
                props.append(words[2])
            elif words[0] == "end_header":
                break
        if fmt != "binary_little_endian" or count is None:
            raise ValueError(f"{path}: need a binary_little_endian PLY with a vertex element")
        raw = np.frombuffer(f.read(count * len(props) * 4), dtype="<f4")
    if raw.size != count * len(props):
        raise ValueError(f"{path}: truncated ({raw.size} of {count * len(props)} values)")
    num_rest = sum(p.startswith("f_rest_") for p in props)
    if (props != _columns(num_rest) or num_rest % 3
            or round(math.sqrt(num_rest // 3 + 1)) ** 2 != num_rest // 3 + 1):
        raise ValueError(f"{path}: properties are not the 3DGS layout: {props[:12]}...")
    t = torch.from_numpy(raw.reshape(count, len(props)).copy())
    k1 = num_rest // 3
    out = {"means": t[:, 0:3], "sh0": t[:, 6:9].reshape(count, 1, 3),
           "opacities": t[:, 9 + num_rest], "scales": t[:, 10 + num_rest:13 + num_rest],
           "quats": t[:, 13 + num_rest:17 + num_rest]}
    if k1:
        out["shN"] = t[:, 9:9 + num_rest].reshape(count, 3, k1).transpose(1, 2).contiguous()
    return {k: v.contiguous() for k, v in out.items()}
