"""avsm_dr.geometry against slow, obvious NumPy references (one ray at a time, the definition
of the interval as the set of t where the point is inside), on random and adversarial rays."""
import math

import numpy as np
import pytest

import avsm_dr  # noqa: F401  (before drjit)
import drjit as dr
from avsm_dr import geometry as G

LO, HI = np.array([-0.5, -0.3, -0.7]), np.array([0.6, 0.4, 0.2])


def box_ref(o, d, lo, hi, t_min=-math.inf):
    """Per ray: the interval {t >= t_min : lo <= o + t d <= hi}, axis by axis in plain Python."""
    out = []
    for oi, di in zip(o, d):
        near, far = t_min, math.inf
        for a in range(3):
            if di[a] == 0.0:
                if not (lo[a] <= oi[a] <= hi[a]):
                    near, far = math.inf, -math.inf
                continue
            inv = 1.0 / di[a]                              # the kernel's reciprocal: exact match
            t1, t2 = (lo[a] - oi[a]) * inv, (hi[a] - oi[a]) * inv
            near, far = max(near, min(t1, t2)), min(far, max(t1, t2))
        out.append((near, far, far > near))
    return [np.array(c) for c in zip(*out)]


def sphere_ref(o, d, c, r, t_min=-math.inf):
    """Per ray: roots of |o + t d - c|^2 = r^2 from the distance of the centre to the line."""
    out = []
    for oi, di in zip(o, d):
        b = float(np.dot(c - oi, di))
        h2 = r * r - float(np.sum((c - oi - b * di) ** 2))
        s = math.sqrt(h2) if h2 > 0 else 0.0
        near, far = max(b - s, t_min), b + s
        out.append((near, far, h2 > 0 and far > near))
    return [np.array(x) for x in zip(*out)]


def adversarial_rays(rng, n=400):
    """Random rays plus rays parallel to each slab (inside, outside, on a face), origins
    inside the box, on faces and corners, and grazing rays along faces and edges."""
    o = rng.uniform(-2, 2, (n, 3))
    d = rng.standard_normal((n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    extra_o, extra_d = [], []
    for a in range(3):
        for val in (LO[a], HI[a], 0.5 * (LO[a] + HI[a]), HI[a] + 0.1, LO[a] - 0.1):
            p = rng.uniform(LO - 0.2, HI + 0.2, 3)
            p[a] = val
            q = rng.standard_normal(3)
            q[a] = 0.0                                     # parallel to slab a
            extra_o.append(p)
            extra_d.append(q / np.linalg.norm(q))
    for _ in range(20):                                   # origin inside
        extra_o.append(rng.uniform(LO, HI))
        q = rng.standard_normal(3)
        extra_d.append(q / np.linalg.norm(q))
    for corner in (LO, HI, np.array([LO[0], HI[1], LO[2]])):   # along an edge, from a corner
        for a in range(3):
            e = np.zeros(3)
            e[a] = 1.0
            extra_o.append(corner - 2 * e)
            extra_d.append(e)
    extra_o.append(np.array([LO[0], 0.0, 0.0]) - np.array([0.0, 0.0, 3.0]))    # grazing a face
    extra_d.append(np.array([0.0, 0.0, 1.0]))
    return np.concatenate([o, extra_o]), np.concatenate([d, extra_d])


@pytest.mark.parametrize("t_min", [-math.inf, 0.0, 0.3])
def test_ray_box_matches_the_reference(rng, t_min):
    o, d = adversarial_rays(rng)
    t0, t1, hit = G.ray_box(o, d, LO, HI, t_min=t_min)
    r0, r1, rh = box_ref(o, d, LO, HI, t_min)
    np.testing.assert_array_equal(hit, rh)
    np.testing.assert_array_equal(t0[hit], r0[rh])        # the same divisions: exact
    np.testing.assert_array_equal(t1[hit], r1[rh])
    # and it is the set of t inside the closed box: midpoints inside, points beyond outside
    tm = 0.5 * (t0[hit] + t1[hit])
    p = o[hit] + tm[:, None] * d[hit]
    assert np.all((p >= LO - 1e-12) & (p <= HI + 1e-12))


def test_ray_box_edge_cases():
    o = np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, HI[1], -3.0], [-3.0, 0.0, 0.0]])
    d = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    t0, t1, hit = G.ray_box(o, d, LO, HI)
    assert hit.tolist() == [True, False, True, True]
    assert (t0[0], t1[0]) == (-0.5, 0.6)                   # origin inside: entry behind it
    assert (t0[1], t1[1]) == (math.inf, -math.inf)         # parallel, outside the y slab: empty
    assert (t0[2], t1[2]) == (LO[2] + 3.0, HI[2] + 3.0)   # grazing the top face (closed slab)
    assert (t0[3], t1[3]) == (LO[0] + 3.0, HI[0] + 3.0)
    t0, _, hit = G.ray_box(o, d, LO, HI, t_min=0.0)
    assert t0[0] == 0.0 and hit[0]


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_ray_box_dr_equals_numpy(rng, dtype):
    """Same operations in the same order: bit for bit in float64; float32 agrees with the
    float64 result of its own (rounded) inputs to float32 rounding."""
    from avsm_dr.area_lights.geometry import kit
    k = kit(dtype)
    o, d = adversarial_rays(rng)
    if dtype == "float32":
        o, d = o.astype(np.float32).astype(np.float64), d.astype(np.float32).astype(np.float64)
    lo, hi = (x.astype(dtype).astype(np.float64) for x in (LO, HI))
    t0, t1, hit = G.ray_box_dr(k.vec_array(o), k.vec_array(d), k.vec(lo), k.vec(hi), t_min=0.0)
    r0, r1, rh = G.ray_box(o, d, lo, hi, t_min=0.0)
    t0, t1, hit = np.asarray(t0, np.float64), np.asarray(t1, np.float64), np.asarray(hit)
    if dtype == "float64":
        np.testing.assert_array_equal(hit, rh)
        np.testing.assert_array_equal(t0, r0)
        np.testing.assert_array_equal(t1, r1)
    else:
        both = hit & rh
        assert (hit != rh).sum() <= 2                      # float32 ties at a face can flip
        np.testing.assert_allclose(t0[both], r0[both], rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(t1[both], r1[both], rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("t_min", [-math.inf, 0.0])
def test_ray_sphere_matches_the_reference(rng, t_min):
    o, d = adversarial_rays(rng)
    c, r = np.array([0.1, 0.2, -0.3]), 0.7
    o = np.concatenate([o, [c - [0.0, 0.7, 3.0], c, c + [0.0, 0.0, 5.0]]])      # tangent, centre, behind
    d = np.concatenate([d, [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]])
    t0, t1, hit = G.ray_sphere(o, d, c, r, t_min=t_min)
    r0, r1, rh = sphere_ref(o, d, c, r, t_min)
    np.testing.assert_array_equal(hit, rh)
    assert not hit[-3]                                     # tangent: no chord of positive length
    np.testing.assert_allclose(t0[hit], r0[rh], rtol=0, atol=1e-14)    # float64 rounding of the dots
    np.testing.assert_allclose(t1[hit], r1[rh], rtol=0, atol=1e-14)
    if t_min == 0.0:
        assert t0[-2] == 0.0 and t1[-2] == pytest.approx(0.7)           # origin at the centre
        assert not hit[-1]                                              # sphere behind the origin
    # per-ray centres and radii (the particles' form)
    cs = c + rng.uniform(-0.2, 0.2, (o.shape[0], 3))
    rs = rng.uniform(0.1, 1.0, o.shape[0])
    t0, t1, hit = G.ray_sphere(o, d, cs, rs)
    for i in range(0, o.shape[0], 37):
        a0, a1, ah = sphere_ref(o[i:i + 1], d[i:i + 1], cs[i], rs[i])
        assert hit[i] == ah[0] and (not ah[0] or abs(t0[i] - a0[0]) < 1e-14)


def test_ray_sphere_dr_equals_numpy_to_rounding(rng):
    from avsm_dr.area_lights.geometry import kit
    k = kit("float64")
    o, d = adversarial_rays(rng)
    c = np.array([0.1, 0.2, -0.3])
    t0, t1, hit = G.ray_sphere_dr(k.vec_array(o), k.vec_array(d), k.vec(c), 0.7, t_min=0.0)
    r0, r1, rh = G.ray_sphere(o, d, c, 0.7, t_min=0.0)
    np.testing.assert_array_equal(np.asarray(hit), rh)
    # float64: dr.dot fuses multiply-adds, einsum does not (a few ulps of |b| <= 4)
    np.testing.assert_allclose(np.asarray(t0)[rh], r0[rh], rtol=0, atol=1e-14)
    np.testing.assert_allclose(np.asarray(t1)[rh], r1[rh], rtol=0, atol=1e-14)


def test_ray_box_dr_accepts_host_corners():
    """NumPy scalar corners become Python floats (NumPy would otherwise take the Dr.Jit
    operand over and return an object array)."""
    from drjit.llvm import Float64
    o = [Float64(-3.0), Float64(0.0), Float64(0.0)]
    d = [Float64(1.0), Float64(0.0), Float64(0.0)]
    t0, t1, hit = G.ray_box_dr(o, d, LO, HI)
    assert type(t0) is Float64 and bool(hit[0])
    assert (float(t0[0]), float(t1[0])) == (LO[0] + 3.0, HI[0] + 3.0)
    assert dr.width(t1) == 1


def test_orthonormal_basis_frame(rng):
    for n in np.concatenate([rng.normal(size=(20, 3)), [[0, 1, 0], [0, -1, 0], [0, 0.995, 0.1]]]):
        u, v, w = G.orthonormal_basis(n)
        m = np.stack([u, v, w])
        np.testing.assert_allclose(m @ m.T, np.eye(3), atol=1e-15)          # float64 rounding
        np.testing.assert_allclose(np.cross(u, v), w, atol=1e-15)
    with pytest.raises(ValueError, match="^w:"):
        G.orthonormal_basis([0.0, 0.0, 0.0])


@pytest.mark.parametrize("box, why", [
    (([0, 0, 0], [1, 0, 1]), "zero-size"), (([0, 0, 0], [1, -1, 1]), "inverted"),
    (([0, 0, np.nan], [1, 1, 1]), "NaN"), (([0, 0, 0], [1, 1, np.inf]), "inf"),
    (([0, 0], [1, 1]), "expected"), ((0.0, 1.0, 2.0), "expected"), (None, "expected")])
def test_check_bbox_refuses_bad_boxes(box, why):
    with pytest.raises(ValueError, match=f"^bounds: .*{why}"):
        G.check_bbox(box, "bounds")
    lo, hi = G.check_bbox(([0, 0, 0], [1, 2, 3]))
    assert lo.dtype == np.float64 and hi.tolist() == [1.0, 2.0, 3.0]
