"""Deep shadow maps in float64 NumPy / plain Python, one texel at a time (checks the
Dr.Jit kernels of avsm_dr.representations.dsm; never imported by the package).

Same specification, written the obvious way:
* optical depth at a depth is the direct sum  tau(d) = sum_i tau_i f_i(d)  (O(S) per
  query, no prefix sums), with the left limit  f_i(d^-)  before zero-length segments;
* level table  L_{n+1} = L_n exp(-sqrt(8 eps_p / L_n))  down to the first  L_N <= eps_p;
  inside each breakpoint interval a vertex where the curve crosses a level not yet passed
  by the previous vertex, its depth rounded to the storage dtype (one ulp past the
  previous vertex when it rounds onto it), its value the exact curve there;
* Lokovic-Veach greedy compression with a slope window ("midslope"), or the subset
  greedy ("curve") checking every intermediate vertex against the chord directly.
"""
from __future__ import annotations

import math

import numpy as np

POLYLINE_SHARE = 0.25
BAND_SHARE = 0.5


def optical_depth(z0, z1, tau, d, left=False):
    """tau(d) (or tau(d^-) with left=True) of one texel: sum_i tau_i f_i(d), direct sum."""
    z0, z1, tau = (np.asarray(x, np.float64) for x in (z0, z1, tau))
    length = z1 - z0
    pos = length > 0
    ramp = np.clip((d - z0) / np.where(pos, length, 1.0), 0.0, 1.0)
    step = (d > z0) if left else (d >= z0)
    return float(np.sum(tau * np.where(pos, ramp, step)))


def levels(eps_p):
    out, lam, level = [], 0.0, 1.0
    while level > eps_p:
        lam += math.sqrt(8.0 * eps_p / level)
        level = math.exp(-lam)
        out.append(lam)
    return out


def _round(x, dtype):
    return float(np.float32(x)) if dtype == "float32" else float(x)


def _next_up(x, dtype):
    """Next value after x representable in dtype."""
    if dtype == "float32":
        return float(np.nextafter(np.float32(x), np.float32(np.inf)))
    return float(np.nextafter(x, np.inf))


def polyline(z0, z1, tau, eps_p, dtype="float64"):
    """Vertices (z, v) of one texel's polyline, within eps_p of the exact curve."""
    if len(z0) == 0:
        return [], []
    lam = levels(eps_p)
    bps = sorted(set(float(x) for x in z0) | set(float(x) for x in z1))
    zs, vs = [], []
    for k, b in enumerate(bps):
        tl = optical_depth(z0, z1, tau, b, left=True)
        tr = optical_depth(z0, z1, tau, b)
        zs.append(b)
        vs.append(math.exp(-tl))
        if np.any((np.asarray(z0) == b) & (np.asarray(z1) == b) & (np.asarray(tau) > 0)):
            zs.append(b)
            vs.append(math.exp(-tr))
        if k + 1 == len(bps):
            break
        nb = bps[k + 1]
        tn = optical_depth(z0, z1, tau, nb, left=True)
        last, tau_last = b, tr
        for L in lam:
            if tr < L < tn and L > tau_last:    # a level the last vertex has not passed
                z = _round(b + (L - tr) * (nb - b) / (tn - tr), dtype)
                z = max(z, _next_up(last, dtype))   # rounded onto the last vertex: one ulp on
                if last < z < nb:
                    zs.append(z)
                    tau_last = optical_depth(z0, z1, tau, z)
                    vs.append(math.exp(-tau_last))
                    last = z
    return zs, vs


def compress_midslope(zs, vs, delta):
    """Lokovic-Veach: slope window from the origin, node on the mid-slope line."""
    if not zs:
        return [], []
    out_z, out_v = [zs[0]], [vs[0]]
    zo, vo = zs[0], vs[0]
    lo, hi, has_w, zp = -math.inf, 0.0, False, zo
    k = 1
    while k < len(zs):
        a, b = max(vs[k] - delta, 0.0), min(vs[k] + delta, 1.0)
        dz = zs[k] - zo
        if dz <= 0:
            if a <= vo <= b:
                zp = zs[k]
            else:                              # step at the origin's depth
                out_z.append(zo)
                out_v.append(vs[k])
                vo = vs[k]
            k += 1
            continue
        nlo, nhi = max(lo, (a - vo) / dz), min(hi, (b - vo) / dz)
        if not has_w:
            nlo = min(nlo, nhi)
        if nlo <= nhi:
            lo, hi, has_w, zp = nlo, nhi, True, zs[k]
            k += 1
        else:                                  # window empty: node at the last fitting depth
            v = max(vo + 0.5 * (lo + hi) * (zp - zo), 0.0)
            out_z.append(zp)
            out_v.append(v)
            zo, vo = zp, v
            lo, hi, has_w = -math.inf, 0.0, False
    if has_w and not (lo <= 0.0 <= hi):
        out_z.append(zp)
        out_v.append(max(vo + 0.5 * (lo + hi) * (zp - zo), 0.0))
    return out_z, out_v


def _chord_fits(zs, vs, o, e, delta):
    """All vertices strictly between o and e within delta of the output from o to e."""
    if zs[e] == zs[o]:
        return True                            # vertical edge: a step through them
    s = (vs[e] - vs[o]) / (zs[e] - zs[o])
    for j in range(o + 1, e):
        line = vs[o] + s * (zs[j] - zs[o]) if zs[j] > zs[o] else vs[o]
        if abs(line - vs[j]) > delta:
            return False
    return True


def compress_curve(zs, vs, delta):
    """Nodes are polyline vertices: extend the chord from the origin while it fits."""
    if not zs:
        return [], []
    keep = [0]
    o, p = 0, 0
    for e in range(1, len(zs)):
        if _chord_fits(zs, vs, o, e, delta):
            p = e
        else:
            keep.append(p)
            o, p = p, e                        # e fits trivially from the new origin
    if p != o:
        flat = all(abs(vs[j] - vs[o]) <= delta for j in range(o + 1, len(zs)))
        if not flat:
            keep.append(p)
    return [zs[i] for i in keep], [vs[i] for i in keep]


def build(offsets, z0, z1, tau, tolerance, placement="midslope", dtype="float64"):
    """Nodes (list of (z array, v array)) of every texel."""
    tau = np.minimum(tau, 1.0e4)
    out = []
    for t in range(len(offsets) - 1):
        s = slice(offsets[t], offsets[t + 1])
        zs, vs = polyline(z0[s], z1[s], tau[s], POLYLINE_SHARE * tolerance, dtype)
        comp = compress_midslope if placement == "midslope" else compress_curve
        nz, nv = comp(zs, vs, BAND_SHARE * tolerance)
        out.append((np.asarray(nz, float), np.asarray(nv, float)))
    return out


def evaluate_nodes(nz, nv, d):
    """Piecewise-linear lookup: 1 in front, last value behind, right value at steps."""
    if len(nz) == 0 or d < nz[0]:
        return 1.0
    j = int(np.searchsorted(nz, d, side="right"))   # first node with z > d
    if j == len(nz):
        return float(nv[-1])
    za, zb, va, vb = nz[j - 1], nz[j], nv[j - 1], nv[j]
    return float(va + (d - za) / (zb - za) * (vb - va))


def exact_curve(z0, z1, tau, d, chunk=256):
    """exp(-tau(d)) of one texel at many depths d (vectorised direct sum, float64)."""
    z0, z1, tau, d = (np.asarray(x, np.float64) for x in (z0, z1, tau, d))
    tau = np.minimum(tau, 1.0e4)
    length = z1 - z0
    pos = length > 0
    safe = np.where(pos, length, 1.0)
    out = np.empty(d.size)
    for s in range(0, d.size, chunk):
        dd = d[s:s + chunk, None]
        f = np.where(pos, np.clip((dd - z0) / safe, 0.0, 1.0), (dd >= z0).astype(float))
        out[s:s + chunk] = np.exp(-(f * tau).sum(axis=1))
    return out
