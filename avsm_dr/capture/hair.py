"""Hair strands: TressFX loading, procedural strands, and strand crossings as segments.

Salvi et al., "Adaptive Volumetric Shadow Maps", EGSR 2010, sec. 3: "for hair we insert
a short segment where the light enters and exits the hair strand". A strand is a
polyline of capsules (radius ``r`` around each of its line segments). A texel ray's
passage through one capsule is the interval hull of its chords through the finite
cylinder and the two end spheres (a capsule is convex); passages through consecutive
capsules of the same strand that overlap (at the joints) are merged, so one crossing of
a strand is one segment ``[t_in, t_out]`` whatever the tessellation, with ::

    T_exit = 1 - opacity,      tau = -ln(1 - opacity)      (opacity per crossing).
"""
from __future__ import annotations

import os
import struct

import numpy as np

from .. import validation as V
from ..geometry import ray_capsule
from ..segments import OPAQUE_OPTICAL_DEPTH

#: Capsules whose footprint rectangles are computed at once (bounds host memory).
CHUNK = 2048
#: Most vertices :func:`procedural_strands` generates (2^24, 400 MB of float64 work arrays).
MAX_VERTICES = 1 << 24


def load_tfx(path, return_w: bool = False):
    """Read a TressFX 4.x ``.tfx`` file (little-endian).

    Header: float32 version, uint32 numHairStrands, uint32 numVerticesPerStrand,
    uint32 offsetVertexPosition, ...; positions are S x V float32 (x, y, z, w) at that
    offset (w = 0 for fixed root vertices).  Returns (S, V, 3) float32 strands
    (and the (S, V) w when ``return_w``)."""
    path = os.fspath(path)
    with open(path, "rb") as f:
        raw = f.read()
    if len(raw) < 16:
        raise ValueError(f"path: {path!r} is too short for a TressFX header")
    version, S, V, off = struct.unpack("<f3I", raw[:16])
    if not (1.0 <= version < 10.0) or S == 0 or V < 2 or off < 16:
        raise ValueError(f"path: {path!r} is not a TressFX file (version {version}, {S} strands, {V} vertices)")
    n = S * V * 4
    if off + 4 * n > len(raw):
        raise ValueError(f"path: {path!r} is truncated ({len(raw)} bytes, positions need {off + 4 * n})")
    xyzw = np.frombuffer(raw, dtype="<f4", count=n, offset=off).reshape(S, V, 4)
    strands = np.ascontiguousarray(xyzw[..., :3], dtype=np.float32)
    if not np.all(np.isfinite(strands)):
        raise ValueError(f"path: {path!r} has non-finite vertex positions")
    return (strands, np.ascontiguousarray(xyzw[..., 3])) if return_w else strands


def procedural_strands(n_strands: int = 300, n_vertices: int = 16, root_center=(0.0, -0.3, 0.0),
                       root_radius: float = 0.2, length: float = 0.6, curl: float = 0.35,
                       seed: int = 0) -> np.ndarray:
    """A tuft of wavy strands rooted on a disc (normal +y) and growing upward.

    Roots uniform on the disc of ``root_radius`` around ``root_center``; each strand
    leaves at a random tilt away from the axis, its direction wandering by
    ``curl`` radians per unit length (deterministic for ``seed``).
    Returns (n_strands, n_vertices, 3) float32."""
    n_strands = V.integer(n_strands, "n_strands", 1)
    n_vertices = V.integer(n_vertices, "n_vertices", 2)
    if n_strands * n_vertices > MAX_VERTICES:
        raise ValueError(f"n_strands: {n_strands} x {n_vertices} vertices exceed {MAX_VERTICES}")
    length = V.real(length, "length", 0.0, open_min=True)
    root_radius = V.real(root_radius, "root_radius", 0.0)
    curl = V.real(curl, "curl", 0.0)
    root_center = V.vec3(root_center, "root_center")
    rng = np.random.default_rng(V.integer(seed, "seed", 0))
    rad = root_radius * np.sqrt(rng.random(n_strands))
    ang = 2 * np.pi * rng.random(n_strands)
    root = np.asarray(root_center, np.float64) + np.stack(
        [rad * np.cos(ang), np.zeros(n_strands), rad * np.sin(ang)], axis=1)
    out = np.empty((n_strands, n_vertices, 3))
    out[:, 0] = root
    tilt = 0.15 + 0.35 * rad / max(root_radius, 1e-9)         # lean outwards from the axis
    d = np.stack([tilt * np.cos(ang), np.ones(n_strands), tilt * np.sin(ang)], axis=1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    seg = length / (n_vertices - 1)
    phase = 2 * np.pi * rng.random((n_strands, 2))
    for k in range(1, n_vertices):
        wob = curl * np.sqrt(seg) * rng.standard_normal((n_strands, 3))
        wave = 0.5 * curl * seg * np.stack([np.sin(phase[:, 0] + 6 * k / n_vertices), np.zeros(n_strands),
                                            np.cos(phase[:, 1] + 6 * k / n_vertices)], axis=1)
        d = d + wob + wave
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        out[:, k] = out[:, k - 1] + seg * d
    return out.astype(np.float32)


def fit_strands(strands: np.ndarray, bmin, bmax, fill: float = 0.8) -> np.ndarray:
    """Uniformly scale and centre strands into the box (bmin, bmax), filling ``fill`` of it."""
    s = V.array(strands, "strands")
    if s.ndim != 3 or s.shape[2] != 3 or s.size == 0:
        raise ValueError(f"strands: expected a non-empty (S, V, 3) array, got shape {s.shape}")
    lo, hi = s.reshape(-1, 3).min(0), s.reshape(-1, 3).max(0)
    bmin, bmax = V.vec3(bmin, "bmin"), V.vec3(bmax, "bmax")
    fill = V.real(fill, "fill", 0.0, open_min=True)
    scale = fill * np.min((bmax - bmin) / np.maximum(hi - lo, 1e-12))
    return ((s - 0.5 * (lo + hi)) * scale + 0.5 * (bmin + bmax)).astype(np.float32)


def merge_crossings(texel, strand, t_in, t_out, capsule=None):
    """Merge overlapping intervals of the same (texel, strand); returns the merged arrays
    (by texel, strand, t_in), and with ``capsule`` (an id per interval) also the smallest
    id of each merged crossing."""
    order = np.lexsort((t_in, strand, texel))
    texel, strand, t_in, t_out = texel[order], strand[order], t_in[order], t_out[order]
    n = texel.size
    group_start = np.ones(n, bool)
    group_start[1:] = (texel[1:] != texel[:-1]) | (strand[1:] != strand[:-1])
    group = np.cumsum(group_start) - 1
    # running max of t_out within each group, via ranks made group-disjoint (exact integers)
    _, rank = np.unique(np.concatenate([t_in, t_out]), return_inverse=True)
    big = 2 * n + 1
    r_in = rank[:n] + group * big
    r_out = rank[n:] + group * big
    run = np.maximum.accumulate(r_out)
    new = group_start.copy()
    new[1:] |= r_in[1:] > run[:-1]
    starts = np.flatnonzero(new)
    out = (texel[starts], strand[starts], t_in[starts], np.maximum.reduceat(t_out, starts))
    return out if capsule is None else out + (np.minimum.reduceat(capsule[order], starts),)


def capture_hair(camera, hair):
    """(texel, z0, z1, tau) float64 NumPy: one segment per crossing of a light ray and a strand,
    and the (S,) int64 draw position of each crossing: its first capsule's index
    ``strand * (V - 1) + j`` (strands in list order, a strand's capsules in vertex order)."""
    s, r, op = hair.validate()
    S, V, _ = s.shape
    pa = s[:, :-1].reshape(-1, 3)
    pb = s[:, 1:].reshape(-1, 3)
    strand_of = np.repeat(np.arange(S), V - 1)
    cid, tex, t_in, t_out = camera.footprint_hits(np.minimum(pa, pb) - r, np.maximum(pa, pb) + r,
                                                  lambda i, o, d: ray_capsule(o, d, pa[i], pb[i], r, t_min=0.0),
                                                  2, CHUNK, "hair")
    texel, _, z0, z1, first = merge_crossings(tex, strand_of[cid], t_in, t_out, cid)
    tau = OPAQUE_OPTICAL_DEPTH if op >= 1.0 else -np.log1p(-op)
    return texel, z0, z1, np.full(texel.size, tau), first
