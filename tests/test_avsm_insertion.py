"""AVSM's ``insertion`` variants (avsm_dr/representations/_avsm_insertion.py) against a slow
float64 NumPy reference of the same algorithms, written here from the module's docstring
(one texel at a time, Python lists), and their properties; ``stream`` stays the default and
bit-identical to it.

Tolerance of the float64 comparisons: node depths must be bit-identical (the reference takes
the same decisions: the same metric formulas in the same operation order) and values agree
to ``VALUE_ATOL = 1e-12`` absolute: a value is a product of <= 40 factors and a few refit
steps (each a handful of float64 operations on numbers <= 1, ~1e-16 each), the kernel's
``exp`` and the reference's NumPy ``exp`` may differ by an ulp, and node values are <= 1, so
differences are ~1e-14; 1e-12 leaves margin without hiding a wrong formula (a wrong refit
moves values by ~1e-3).
"""
import math

import numpy as np
import pytest

import avsm_dr as ad
import drjit as dr
from avsm_dr import backend
from avsm_dr.representations._avsm_insertion import INSERTIONS, KEEP_TOL, remove_refit
from cases import random_segments, to_segments
from reference import exact_ref

VARIANTS = [k for k in INSERTIONS if k != "stream"]
VALUE_ATOL = 1e-12


# ----------------------------------------------------------------------------
# float64 NumPy reference (one texel, Python lists of floats)
# ----------------------------------------------------------------------------
def _bracket(d, t, x):
    dl, tl, dr_, tr = x, 1.0, x, 1.0
    n = len(d)
    for k in range(n):
        if d[k] <= x:
            nxt = min(k + 1, n - 1)
            dl, tl, dr_, tr = d[k], t[k], d[nxt], t[nxt]
    return dl, tl, dr_, tr


def _curve_at(d, t, x):
    """T(x) (cancellation-free form of avsm.curve_at) and whether the stored nodes make it 0."""
    dl, tl, dr_, tr = _bracket(d, t, x)
    dd = dr_ - dl
    w = (dr_ - x) / (dd if dd > 0 else 1.0)
    value = min(tr + (tl - tr) * w, tl)
    return value, tl == 0 and (tr == 0 or x == dl)


def _interp_exp(d, t, x):
    """T(x) interpolated exponentially between the bracketing nodes (avsm.lerp, mode 'exp')."""
    dl, tl, dr_, tr = _bracket(d, t, x)
    dd = dr_ - dl
    w = min(max((x - dl) / (dd if dd > 0 else 1.0), 0.0), 1.0)
    return tl * math.exp(w * (math.log(tr) - math.log(tl))) if tl > 0 and tr > 0 else tl + w * (tr - tl)


def _insert(d, t, used, a, b, ts, ta, full=False, tau=None):
    """The list with segment [a, b] inserted: n + 2 nodes (avsm.insert_segment; ``tau``: the
    exponential ramp exp(-tau (d - a) / (b - a)) and T(b) interpolated exponentially)."""
    n = len(d)
    tb = (_curve_at(d, t, b)[0] if tau is None else _interp_exp(d, t, b)) * ts
    length = b - a
    inv_len = 1.0 / (length if length > 0 else 1.0)
    e, x, scaled = 0, 1, []
    for k in range(n):
        ramp = min(ts + (1.0 - ts) * ((b - d[k]) * inv_len), 1.0)
        if tau is not None:
            ramp = math.exp(-tau * min(max((d[k] - a) * inv_len, 0.0), 1.0))
        inner = (ts if d[k] >= b else ramp) if d[k] > a else 1.0
        real = (full and k < n - 1) or k < used
        if real:
            e += d[k] <= a
            x += d[k] <= b
        scaled.append(t[k] * (inner if real else ts))
    od = d[:e] + [a] + d[e:x - 1] + [b] + d[x - 1:]
    ot = scaled[:e] + [ta] + scaled[e:x - 1] + [tb] + scaled[x - 1:]
    return od, ot


def _l2_deltas(c, dll, dl, di, dr_, drr, move_l, move_r):
    """Unclipped least-squares (delta_l, delta_r, p)."""
    l0, l1, l2 = dl - dll, dr_ - dl, drr - dr_
    p = (di - dl) / (l1 if l1 > 0 else 1.0)
    a11 = 2 * (l0 + l1) if move_l else 1.0
    a22 = 2 * (l1 + l2) if move_r else 1.0
    a12 = l1 if move_l and move_r else 0.0
    b1 = -c * (2 - p) if move_l else 0.0
    b2 = -c * (1 + p) if move_r else 0.0
    det = a11 * a22 - a12 * a12
    inv = 1 / det if det > 0 else 0.0
    return (((b1 * a22 - a12 * b2) * inv, (a11 * b2 - a12 * b1) * inv) if det > 0 else (0.0, 0.0)) + (p,)


def _refit(c, dll, dl, di, dr_, drr, tll, tl, tr, trr, move_l, move_r, fit):
    if fit == "area":
        w = (dr_ - dll if move_l else 0.0) + (drr - dl if move_r else 0.0)
        delta = -c / w if w > 0 else 0.0
        dlt_l, dlt_r = (delta if move_l else 0.0), (delta if move_r else 0.0)
    else:
        dlt_l, dlt_r, _ = _l2_deltas(c, dll, dl, di, dr_, drr, move_l, move_r)
    hi = tll if move_l else tl
    lo = trr if move_r else tr
    ul = min(max(tl + dlt_l, lo), hi)
    ur = min(max(tr + dlt_r, lo), hi)
    if ur > ul:
        ul = ur = (ul + ur) * 0.5
    return (ul if move_l else tl), (ur if move_r else tr)


def _remove(d, t, fit, metric, gap=None):
    """Remove the interior node of least metric (ties: the deepest), refit its neighbours;
    ``gap``: a list that gets the removed node's distance to its neighbours' chord."""
    n = len(d)
    best, idx = None, None
    for i in range(1, n - 1):
        c = (d[i + 1] - d[i - 1]) * (t[i + 1] - t[i]) - (d[i + 1] - d[i]) * (t[i + 1] - t[i - 1])
        if metric == "area":
            m = abs(c)
        else:
            w = d[i + 1] - d[i - 1]
            m = c * c / (w if w > 0 else 1.0)
        if metric == "post":                       # the L2 left after the unclipped refit
            dl_, dr__, p = _l2_deltas(c, d[max(i - 2, 0)], d[i - 1], d[i], d[i + 1], d[min(i + 2, n - 1)],
                                      i >= 2, i <= n - 3)
            m = max(m + 0.5 * c * ((2 - p) * dl_ + (1 + p) * dr__), 0.0)
        if best is None or m <= best:
            best, idx, c_best = m, i, c
    i = idx
    if gap is not None:
        w = d[i + 1] - d[i - 1]
        gap.append(abs(c_best) / w if w > 0 else 0.0)
    nd, nt = d[:i] + d[i + 1:], t[:i] + t[i + 1:]
    if fit is not None:
        move_l, move_r = i >= 2, i <= n - 3
        ul, ur = _refit(c_best, d[max(i - 2, 0)], d[i - 1], d[i], d[i + 1], d[min(i + 2, n - 1)],
                        t[max(i - 2, 0)], t[i - 1], t[i + 1], t[min(i + 2, n - 1)], move_l, move_r, fit)
        nt[i - 1], nt[i] = ul, ur
    return nd, nt


def _phi(a):
    """((1 - e^-a) / a, (1 - (1 + a) e^-a) / a^2), a >= 0 (series below 1e-3)."""
    if a < 1e-3:
        return 1 - a / 2 + a * a / 6 - a ** 3 / 24, 0.5 - a / 3 + a * a / 8 - a ** 3 / 30
    return -math.expm1(-a) / a, (-math.expm1(-a) - a * math.exp(-a)) / (a * a)


def _final_fit(dw, tw, d, t, last):
    """Least-squares values on the nodes (d, t) (node 0 and node `last` fixed, the nodes
    behind it kept) of the linear lookup against the exponential interpolation of the
    working list (dw, tw) over [d_0, d_last]: the normal equations of the hat functions,
    a dense solve; clipped to [t_last, 1], then the mean of the running min and max."""
    n = len(d)
    b = np.zeros(n)
    M = np.zeros((n, n))
    for k in range(last):                 # final piece k: [d_k, d_k+1], its working pieces
        h = d[k + 1] - d[k]
        if h <= 0:
            continue
        M[k, k] += h / 3
        M[k + 1, k + 1] += h / 3
        M[k, k + 1] += h / 6
        M[k + 1, k] += h / 6
        s0 = s1 = 0.0
        for j in range(len(dw) - 1):
            x0, x1 = dw[j], dw[j + 1]
            if not (x0 >= d[k] and x1 <= d[k + 1] and x1 > x0):
                continue
            v0, v1, L = tw[j], tw[j + 1], x1 - x0
            if v0 > 0 and v1 > 0:
                p1, p2 = _phi(max(math.log(v0) - math.log(v1), 0.0))
                m0, m1 = L * v0 * p1, L * L * v0 * p2
            else:
                m0, m1 = L * (v0 + v1) / 2, L * L * (v0 + 2 * v1) / 6
            s0 += m0
            s1 += m1 + (x0 - d[k]) * m0
        b[k] += s0 - s1 / h
        b[k + 1] += s1 / h
    free = [k for k in range(1, last) if M[k, k] > 0]
    x = np.array(t, np.float64)
    if free:
        fixed = [k for k in range(n) if k not in free]
        rhs = b[free] - M[np.ix_(free, fixed)] @ x[fixed]
        x[free] = np.linalg.solve(M[np.ix_(free, free)], rhs)
    x[:last + 1] = np.clip(x[:last + 1], t[last], 1.0)
    fwd = np.minimum.accumulate(x)
    bwd = np.maximum.accumulate(x[::-1])[::-1]
    out = list(t)
    for k in range(1, last):
        out[k] = 0.5 * (fwd[k] + bwd[k])
    return out


def reference_texel(z0, z1, tau, N, far, insertion, sort=False):
    """(depths, values) of one texel: the kernel's two phases on N + spare nodes, in float64,
    then the spare nodes removed by the 'post' metric (then the final fit)."""
    fit, metric, stage, spare, ramp, final_fit = INSERTIONS[insertion]
    N0, N = N, N + spare
    order = np.lexsort((z1, z0)) if sort else np.arange(len(z0))
    segs = [(float(z0[s]), float(z1[s]), float(np.exp(-tau[s]))) for s in order]
    taus = [float(tau[s]) if ramp == "exp" else None for s in order]

    def entry(d, t, a, k):        # (T(a), whether the stored nodes make it 0) for segment k
        ta, zero = _curve_at(d, t, a)
        return (ta if taus[k] is None else _interp_exp(d, t, a)), zero
    d, t, used, i, done, compressed = [far] * N, [1.0] * N, 0, 0, False, False
    gaps = []                             # chord gaps of the removals while streaming
    while i < len(segs) and used + 2 <= N and not done:          # room left: no compression
        a, b, ts = segs[i]
        ta, zero = entry(d, t, a, i)
        if not zero:
            od, ot = _insert(d, t, used, a, b, ts, ta, tau=taus[i])
            d, t, used = od[:N], ot[:N], used + 2
        done = sort and zero
        i += 1
    while i < len(segs) and not done:                            # full
        if stage == 1:
            a, b, ts = segs[i]
            ta, zero = entry(d, t, a, i)
            if not zero:
                compressed = True
                od, ot = _insert(d, t, used, a, b, ts, ta, full=True, tau=taus[i])
                for _ in range(2):
                    od, ot = _remove(od, ot, fit, metric, gaps)
                d, t = od, ot
            done = sort and zero
            i += 1
            continue
        grow = used
        for _ in range(stage):
            n = len(d)
            active = i < len(segs) and not done
            put = False
            if active:
                a, b, ts = segs[i]
                ta, zero = _curve_at(d, t, a)
                put = not zero
                done = sort and zero
                i += 1
            if put:
                d, t = _insert(d, t, grow, a, b, ts, ta)
                grow += 2
            else:                     # two copies of the last node (real copies iff it is real)
                d, t = d + [d[-1]] * 2, t + [t[-1]] * 2
                grow += 2 if grow == n else 0
        for _ in range(2 * stage):
            d, t = _remove(d, t, fit, metric)
    if spare:          # the used nodes (all once a segment compressed) compressed to N0
        live = len(d) if compressed else used
        dw, tw = d[:live], t[:live]
        d, t = (d[:live], t[:live]) if live > N0 else (d[:N0], t[:N0])
        while len(d) > N0:
            d, t = _remove(d, t, fit, "post")
        if final_fit and max(gaps, default=0.0) <= KEEP_TOL:
            t = _final_fit(dw, tw, d, t, min(live, N0) - 1)
    return np.array(d), np.array(t)


def reference_nodes(seg, rep):
    h = seg.numpy()
    off = h["offsets"]
    T, N, far = len(off) - 1, rep.N, rep.params["far"]
    D, V = np.full((T, N), far, np.float64), np.ones((T, N))
    for k in range(T):
        s = slice(off[k], off[k + 1])
        if off[k + 1] > off[k]:
            D[k], V[k] = reference_texel(h["z0"][s], h["z1"][s], h["optical_depth"][s], N, far,
                                         rep.params["insertion"], rep.params["sort"])
    return D, V


def _adversarial_segments(dtype="float64"):
    """Coincident, zero-length, opaque, huge optical depth, duplicate and nested segments;
    texels of exactly N - 1, N, N + 1 segments for N = 4; a tiny and a huge depth range."""
    z0 = [0.0, 0.0, 0.5, 0.5, 0.5, 1e-7, 0.9, 1.0, 0.2, 0.2, 0.2, 0.3]
    z1 = [0.0, 1.0, 0.5, 0.5, 0.6, 2e-7, 1.0, 1.0, 0.4, 0.4, 0.9, 0.35]
    tr = [0.0, 0.5, 1.0, 0.0, 1e-30, 0.9, 0.0, 0.3, 0.5, 0.5, 0.7, 0.2]
    texels = [(z0, z1, tr)]
    rng = np.random.default_rng(7)
    for count in (3, 4, 5, 9):                                  # around N = 4 and 2 N + 1
        a = np.sort(rng.uniform(0, 1, count))
        texels.append((a, a + rng.uniform(0, 0.3, count), rng.uniform(0.2, 0.95, count)))
    a = np.linspace(0, 1, 12)                                   # contiguous, equal segments
    texels.append((a[:-1], a[1:], np.full(11, 0.8)))
    texels.append((a[:-1] * 1e-6, a[1:] * 1e-6, np.full(11, 0.8)))
    texels.append((a[:-1] * 1e6 + 1e6, a[1:] * 1e6 + 1e6, np.full(11, 0.8)))
    texels.append(([0.4] * 6, [0.4] * 6, [0.5] * 6))            # all at one depth
    texels.append(([0.1, 0.2, 0.3, 0.4, 0.5, 0.6], [0.9] * 6, [0.9] * 6))      # nested, common exit
    z0 = np.concatenate([np.asarray(x[0], float) for x in texels])
    z1 = np.concatenate([np.asarray(x[1], float) for x in texels])
    trn = np.concatenate([np.asarray(x[2], float) for x in texels])
    offsets = np.concatenate([[0], np.cumsum([len(x[0]) for x in texels])])
    return ad.Segments.from_arrays(offsets, z0, z1, transmittance=trn, dtype=dtype)


# ----------------------------------------------------------------------------
def test_schema_lists_the_insertions():
    p = ad.describe("avsm")["params"]["insertion"]
    assert p["type"] == "choice" and p["default"] == "stream"
    assert p["choices"] == list(INSERTIONS)
    seg = ad.Segments.from_arrays([0, 1], [0.2], [0.4], optical_depth=[0.5])
    with pytest.raises(ValueError, match="insertion"):
        ad.build("avsm", seg, insertion="nope")


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_stream_is_bit_identical_to_the_default(rng, dtype):
    seg = to_segments(random_segments(rng, texels=80, max_count=30), dtype)
    for kw in ({"nodes": 8}, {"nodes": 5, "sort": True}, {"nodes": 4, "_split": False}, {"nodes": 2}):
        a = ad.build("avsm", seg, **kw)
        b = ad.build("avsm", seg, insertion="stream", **kw)
        for x, y in zip(a.nodes_numpy(), b.nodes_numpy()):
            np.testing.assert_array_equal(x, y)
        assert a.stats == b.stats


@pytest.mark.parametrize("insertion", list(INSERTIONS))       # 'stream' too: the reference's own check
@pytest.mark.parametrize("nodes", [2, 3, 4, 8, 13])
@pytest.mark.parametrize("sort", [False, True])
def test_variants_match_reference_float64(rng, insertion, nodes, sort):
    seg = to_segments(random_segments(rng, texels=40, max_count=25), "float64")
    rep = ad.build("avsm", seg, nodes=nodes, sort=sort, insertion=insertion)
    D, V = rep.nodes_numpy()
    Dr, Vr = reference_nodes(seg, rep)
    np.testing.assert_array_equal(D, Dr)
    np.testing.assert_allclose(V, Vr, rtol=0, atol=VALUE_ATOL)


@pytest.mark.parametrize("insertion", list(INSERTIONS))
@pytest.mark.parametrize("nodes", [3, 4, 6])
def test_variants_match_reference_on_adversarial_texels(insertion, nodes):
    seg = _adversarial_segments()
    for sort in (False, True):
        rep = ad.build("avsm", seg, nodes=nodes, sort=sort, insertion=insertion)
        D, V = rep.nodes_numpy()
        Dr, Vr = reference_nodes(seg, rep)
        np.testing.assert_array_equal(D, Dr)
        np.testing.assert_allclose(V, Vr, rtol=0, atol=VALUE_ATOL)
        assert np.all(np.isfinite(V)) and np.all((V >= 0) & (V <= 1))


@pytest.mark.parametrize("insertion", VARIANTS)
def test_float32_kernel_agrees_with_the_float64_reference(rng, insertion):
    """float32 kernel vs float64 reference on float32-representable input: node layouts agree
    except where near-ties of the metric flip (counted and bounded, as for 'stream' in
    test_avsm.py); on the texels that agree, values within float32 rounding of products of
    <= 30 factors and refit steps (5e-6).  The final fit's target is linear on a piece that
    ends at T = 0 (the lookup's convention), and behind an opaque segment float32 reaches 0
    where float64 holds ~1e-130: texels with such a segment are left out for that variant."""
    data = random_segments(rng, texels=200, max_count=30)
    seg = to_segments(data, "float32")
    rep = ad.build("avsm", seg, nodes=8, insertion=insertion)
    D, V = rep.nodes_numpy()
    Dr, Vr = reference_nodes(seg, rep)
    same = np.all(D == Dr, axis=1)
    assert same.mean() > 0.9
    if INSERTIONS[insertion][5]:
        underflow = np.exp(-seg.numpy()["optical_depth"].astype(np.float32)) == 0
        per_texel = np.diff(np.concatenate([[0], np.cumsum(underflow)])[data["offsets"]])
        same &= per_texel == 0
        assert same.mean() > 0.5
    np.testing.assert_allclose(V[same], Vr[same], atol=5e-6)


@pytest.mark.parametrize("insertion", list(INSERTIONS))
def test_properties(rng, insertion):
    """Values in [0, 1], non-increasing, the first one 1 (nothing in front of the first entry),
    the last one the exact transmittance behind everything (never refitted); the counters
    add up."""
    data = random_segments(rng, texels=100, max_count=40)
    seg = to_segments(data, "float64")
    for nodes in (2, 5, 8):
        rep = ad.build("avsm", seg, nodes=nodes, insertion=insertion)
        D, V = rep.nodes_numpy()
        assert np.all((V >= 0) & (V <= 1)) and np.all(np.diff(V, axis=1) <= 0)
        assert np.all(np.diff(D, axis=1) >= 0)
        nz = np.diff(data["offsets"]) > 0
        np.testing.assert_array_equal(V[nz, 0], 1.0)
        behind = exact_ref.evaluate(data["offsets"], data["z0"], data["z1"], data["tau"],
                                    np.arange(100), np.full(100, rep.params["far"]))
        np.testing.assert_allclose(V[:, -1], behind, atol=1e-12)
        s = rep.stats
        assert s["lanes"] == nz.sum() and s["segments"] == data["z0"].size
        assert s["skipped"] + s["compressed"] <= s["segments"]


def _polyline_area(d, t):
    return sum(0.5 * (d[k + 1] - d[k]) * (t[k + 1] + t[k]) for k in range(len(d) - 1))


def _removal(d, t, fit, metric="area"):
    F = backend.types().Float64
    nd, nt = remove_refit([F(x) for x in d], [F(x) for x in t], fit, metric)
    return [x[0] for x in nd], [x[0] for x in nt]


def test_area_refit_keeps_the_area():
    """One removal with 'area' refit keeps the area under the polyline when no clip binds."""
    d = [0.0, 1.0, 2.0, 2.5, 4.0, 5.0, 6.0]
    t = [1.0, 0.8, 0.5, 0.42, 0.3, 0.15, 0.1]
    nd, nt = _removal(d, t, "area")
    assert len(nd) == 6 and nd[0] == 0 and nd[-1] == 6 and nt[0] == 1 and nt[-1] == 0.1
    i = next(k for k, x in enumerate(d) if x not in nd)                # the removed node
    assert 2 <= i <= len(d) - 3 and nt[i - 1] != t[i - 1] and nt[i] != t[i + 1]   # both neighbours moved
    assert math.isclose(_polyline_area(nd, nt), _polyline_area(d, t), rel_tol=1e-14)


def test_l2_refit_is_the_least_squares_fit():
    """One removal with 'l2' refit: the neighbours' values minimise the L2 distance to the
    polyline before the removal over [d_ll, d_rr] (checked against a dense least-squares
    solve, Simpson's rule on every piece: exact for the quadratic integrands)."""
    d = [0.0, 1.0, 2.0, 2.6, 4.0, 5.0, 6.5]
    t = [1.0, 0.95, 0.6, 0.3, 0.25, 0.2, 0.18]
    nd, nt = _removal(d, t, "l2", "l2")
    gone = [x for x in d if x not in nd]
    assert len(gone) == 1
    i = d.index(gone[0])
    ll, rr = i - 2, i + 2
    assert 0 <= ll and rr < len(d)                          # both neighbours movable here
    xs = sorted(set(d[ll:rr + 1]))
    pts, wts = [], []
    for a, b in zip(xs[:-1], xs[1:]):
        pts += [a, (a + b) / 2, b]
        wts += [(b - a) / 6, 4 * (b - a) / 6, (b - a) / 6]
    pts, wts = np.array(pts), np.sqrt(np.array(wts))
    new_d = d[ll:i] + d[i + 1:rr + 1]

    def hat(j):
        return np.interp(pts, new_d, np.eye(len(new_d))[j])

    fixed = t[ll] * hat(0) + t[rr] * hat(3)
    A = np.stack([hat(1), hat(2)], 1) * wts[:, None]
    rhs = (np.interp(pts, d[ll:rr + 1], t[ll:rr + 1]) - fixed) * wts
    want = np.linalg.lstsq(A, rhs, rcond=None)[0]
    np.testing.assert_allclose([nt[i - 1], nt[i]], want, rtol=0, atol=1e-13)


def test_post_metric_removes_the_node_of_least_refitted_l2():
    """'post' removes the node whose removal leaves the least L2 after the least-squares refit
    of its neighbours (dense solve, Simpson's rule on every piece); here the chord metric 'l2'
    would remove another node (residuals 1e-5 against 3e-5 and more)."""
    d = [0.0, 1.7, 1.8, 2.3, 2.9, 3.1, 5.5]
    t = [1.0, 0.83, 0.81, 0.62, 0.5, 0.05, 0.04]

    def residual(i):
        ll, rr = max(i - 2, 0), i + 2
        xs = d[ll:rr + 1]
        pts = np.concatenate([[a, (a + b) / 2, b] for a, b in zip(xs[:-1], xs[1:])])
        wts = np.sqrt(np.concatenate([[b - a, 4 * (b - a), b - a] for a, b in zip(xs[:-1], xs[1:])]) / 6)
        new_d, new_t = d[ll:i] + d[i + 1:rr + 1], t[ll:i] + t[i + 1:rr + 1]
        move = [j for j in (i - 1, i) if j - ll != 0]                # the first node stays
        hats = np.stack([np.interp(pts, new_d, np.eye(len(new_d))[j - ll]) for j in move], 1)
        fixed = np.interp(pts, new_d, [0.0 if k + ll in move else v for k, v in enumerate(new_t)])
        rhs = (np.interp(pts, xs, t[ll:rr + 1]) - fixed) * wts
        x = np.linalg.lstsq(hats * wts[:, None], rhs, rcond=None)[0]
        return float(np.sum((hats * wts[:, None] @ x - rhs) ** 2))

    res = [residual(i) for i in range(1, 5)]
    gone = {m: next(i for i, x in enumerate(d) if x not in _removal(d, t, "l2", m)[0]) for m in ("l2", "post")}
    assert gone["post"] == 1 + int(np.argmin(res)) and gone["l2"] != gone["post"]


def test_spare_nodes_change_nothing_without_overflow(rng):
    """Texels of at most N / 2 segments never compress: 'spare_refit_l2' keeps them as
    'refit_l2' does (the spare nodes are clear nodes, removed first at the end)."""
    seg = to_segments(random_segments(rng, texels=60, max_count=4), "float64")
    a = ad.build("avsm", seg, nodes=8, insertion="refit_l2").nodes_numpy()
    b = ad.build("avsm", seg, nodes=8, insertion="spare_refit_l2").nodes_numpy()
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)


def test_exponential_ramps_keep_the_exact_curve_in_every_order(rng):
    """Texels that never compress (at most N / 2 overlapping segments): 'spare_exp' holds the
    exact curve's values at its nodes in every insertion order (products of exact uniform-density
    factors); the linear ramps of 'spare_refit_l2' do not, where segments overlap (1e-3 and more)."""
    data = random_segments(rng, texels=60, max_count=4, opaque_fraction=0.0, zero_fraction=0.0)
    seg = to_segments(data, "float64")
    texel = np.repeat(np.arange(60), 8)
    for order in ("depth", "reverse_depth", "random"):
        s = seg.in_order(order, seed=1 if order == "random" else None)
        D, V = ad.build("avsm", s, nodes=8, insertion="spare_exp").nodes_numpy()
        exact = exact_ref.evaluate(data["offsets"], data["z0"], data["z1"], data["tau"], texel, D.ravel())
        np.testing.assert_allclose(V.ravel(), exact, rtol=0, atol=1e-12)
    D, V = ad.build("avsm", seg.in_order("depth"), nodes=8, insertion="spare_refit_l2").nodes_numpy()
    exact = exact_ref.evaluate(data["offsets"], data["z0"], data["z1"], data["tau"], texel, D.ravel())
    assert np.max(np.abs(V.ravel() - exact)) > 1e-3


def test_final_fit_is_the_least_squares_fit_to_the_exact_curve(rng):
    """Contiguous segments of uniform density (a ray march): streaming removes only coincident
    nodes, so 'spare_exp_fit' fits every texel; its values are the least-squares values of the
    linear lookup on its nodes against the exact curve over the node range (first and last
    fixed), checked against a dense solve on 20000 midpoints of the exact curve (exact_ref;
    the midpoint rule's error ~1e-9), and each texel's L2 is below 'spare_exp''s."""
    counts = rng.integers(3, 12, 40)
    offsets = np.concatenate([[0], np.cumsum(counts)])
    z0, z1 = [], []
    for c in counts:
        edges = np.cumsum(rng.uniform(0.02, 0.2, c + 1))
        z0 += list(edges[:-1])
        z1 += list(edges[1:])
    tau = rng.uniform(0.05, 1.5, offsets[-1])
    seg = ad.Segments.from_arrays(offsets, z0, z1, optical_depth=tau, dtype="float64")
    order = seg.in_order("random", seed=3)
    D, V = ad.build("avsm", order, nodes=4, insertion="spare_exp_fit").nodes_numpy()
    D0, V0 = ad.build("avsm", order, nodes=4, insertion="spare_exp").nodes_numpy()
    np.testing.assert_array_equal(D, D0)
    checked = 0
    for k in range(counts.size):
        last = int(np.searchsorted(D[k], z1[offsets[k + 1] - 1], side="right")) - 1
        z = D[k, 0] + (np.arange(20000) + 0.5) / 20000 * (D[k, last] - D[k, 0])
        ex = exact_ref.evaluate(offsets, np.array(z0), np.array(z1), tau, np.full(z.size, k), z)
        hats = np.stack([np.interp(z, D[k, :last + 1], np.eye(last + 1)[j]) for j in range(last + 1)], 1)
        rhs = ex - hats[:, 0] * V[k, 0] - hats[:, last] * V[k, last]
        want = np.linalg.lstsq(hats[:, 1:last], rhs, rcond=None)[0]
        assert np.mean((hats @ V[k, :last + 1] - ex) ** 2) < np.mean((hats @ V0[k, :last + 1] - ex) ** 2)
        if np.all(np.diff(np.r_[V[k, 0], want, V[k, last]]) <= 0):      # no clip or projection at work
            np.testing.assert_allclose(V[k, 1:last], want, rtol=0, atol=1e-7)
            checked += 1
    assert checked >= 30


@pytest.mark.parametrize("insertion", VARIANTS)
def test_gradients_match_finite_differences(rng, insertion):
    """d sum(w T) / d optical depth, reverse and forward mode, against central differences
    (float64, eps = 1e-6 leaves the node layout and the refits' clips unchanged: 1e-6 abs)."""
    F64 = backend.types().Float64
    data = random_segments(rng, texels=12, max_count=14, opaque_fraction=0.0, zero_fraction=0.0)
    tex = np.repeat(np.arange(12), 6)
    depth = rng.uniform(0, 1, tex.size)
    w = rng.normal(size=tex.size)

    def loss(tau, grad=False):
        t = F64(tau)
        if grad:
            dr.enable_grad(t)
        seg = ad.Segments.from_arrays(data["offsets"], data["z0"], data["z1"], optical_depth=t)
        return t, dr.sum(ad.build("avsm", seg, nodes=4, insertion=insertion).eval(tex, depth) * F64(w))

    t, L = loss(data["tau"], grad=True)
    dr.backward(L)
    g = dr.grad(t).numpy()
    eps = 1e-6
    for j in rng.choice(data["tau"].size, size=10, replace=False):
        tp, tm = data["tau"].copy(), data["tau"].copy()
        tp[j] += eps
        tm[j] -= eps
        fd = (loss(tp)[1][0] - loss(tm)[1][0]) / (2 * eps)
        assert abs(g[j] - fd) < 1e-6, (j, g[j], fd)
    direction = rng.normal(size=data["tau"].size)
    t, L = loss(data["tau"], grad=True)
    dr.set_grad(t, F64(direction))
    dr.forward_to(L)
    np.testing.assert_allclose(dr.grad(L)[0], np.dot(g, direction), rtol=1e-9, atol=1e-12)
