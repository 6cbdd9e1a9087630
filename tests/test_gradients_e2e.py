"""Gradients end to end: density grid (or particle densities) -> capture -> representation
-> transmittance at receivers -> loss, against central finite differences in float64;
reverse vs forward mode; loop bounds; checkpointed / recomputed reverse paths; the
inverse problem's building blocks (avsm_dr.reconstruction, avsm_dr.representations._loops).

Tolerances (float64 throughout, eps = 1e-6 central differences): truncation
O(eps^2 |f'''|) ~ 1e-12 and cancellation ~ 1e-16 |f| / eps ~ 1e-10 |f| with |f| <= 10,
so |g - fd| <= 1e-7 + 1e-6 |fd|.  Reverse vs forward mode: same arithmetic in another
order, rtol 1e-9.
"""
import copy
import math

import numpy as np
import pytest

import avsm_dr as ad
import drjit as dr
from avsm_dr import backend, reconstruction as inv
from avsm_dr.checks import check_gradients
from avsm_dr.representations import _loops as ck
from avsm_dr.representations.exact import Exact
from avsm_dr.scene import DirectionalLight, Particles, Scene

KINDS = ["exact", "fom", "osm", "avsm", "dsm"]
EPS = 1e-6
T64 = backend.types()


def _scene(rng, shape=(5, 6, 5)):
    """A small box of strictly positive, smooth-ish density (no empty voxels, so AVSM's
    area metrics have no ties) and an oblique directional light."""
    bmin, bmax = np.array([-0.5, 0.0, -0.5]), np.array([0.5, 1.2, 0.5])
    dens = 0.4 + 2.0 * rng.random(shape)
    probes = bmin + rng.random((40, 3)) * (bmax - bmin)                 # receivers inside the box
    behind = inv.receiver_grid((bmin, bmax), DirectionalLight((1.0, -0.4, 0.3)), 4)
    rec = np.concatenate([probes, behind])
    return Scene("test", DirectionalLight((1.0, -0.4, 0.3)), rec, density=dens, bbox=(bmin, bmax)), dens


def _loss(scene, x, kind, w, **kw):
    sh = inv.shadow(scene, x, kind=kind, resolution=64, epsilon=1e-12, **kw)
    return dr.sum(sh.T * T64.Float64(w)), sh


def _tensor(d, grad=False):
    return inv.density_tensor(d, dtype="float64", grad=grad)


# ----------------------------------------------------------------------------
# density grid -> capture -> every differentiable representation
# ----------------------------------------------------------------------------
@pytest.mark.parametrize("kind", KINDS)
def test_grid_gradients_match_finite_differences(kind):
    """Reverse mode against central differences (4 largest |g| + 4 random voxels) and
    against forward mode along a random direction (avsm_dr.checks.check_gradients)."""
    rng = np.random.default_rng(7)
    scene, dens = _scene(rng)
    w = rng.normal(size=scene.receivers.shape[0])
    L, sh = _loss(scene, _tensor(dens), kind, w)
    assert sh.capture.segments.dtype == "float64"

    primal = accept = None
    if kind == "dsm":
        # node depths held fixed: the primal of the same layout with values on the exact curve
        base = sh.rep
        assert base.differentiable and not np.any(base.node_left)   # no zero-length segments here
        tex = np.repeat(np.arange(base.n_texels), base.node_counts)
        zn = np.asarray(dr.detach(base.node_depth).numpy())

        def primal(d):
            s = inv.shadow(scene, _tensor(d), kind="exact", resolution=64, epsilon=1e-12)
            rep = copy.copy(base)
            rep.node_value = Exact(s.capture.segments).eval(tex, zn)
            T = s.capture.transmittance(rep, scene.receivers)
            return float(dr.sum(T * T64.Float64(w))[0])
        assert primal(dens) == pytest.approx(L[0], abs=1e-12)
    elif kind == "avsm":
        def layout(d):
            rep = _loss(scene, _tensor(d), kind, w)[1].rep
            return [np.asarray(a.numpy()) for a in rep.depths] + [rep.used]
        base_layout = layout(dens)

        def accept(dp, dm):                                          # FD straddles a layout change?
            return all(np.array_equal(a, b) for d_ in (dp, dm) for a, b in zip(layout(d_), base_layout))

    chk = check_gradients(lambda x: _loss(scene, x, kind, w)[0], _tensor(dens), fd=8, eps=EPS,
                          primal=primal, accept=accept, rng=rng)
    assert chk.ok, chk
    assert np.all(np.isfinite(chk.gradient)) and np.abs(chk.gradient).max() > 1e-3
    assert len(chk.indices) >= 6


def test_empty_voxels_receive_gradients():
    """keep_zero=True: voxels that are 0 (an empty start) still get gradients."""
    rng = np.random.default_rng(1)
    scene, dens = _scene(rng)
    zero = np.zeros_like(dens)
    x = _tensor(zero, grad=True)
    L, sh = _loss(scene, x, "fom", np.ones(scene.receivers.shape[0]))
    dr.backward(L)
    g = np.asarray(dr.grad(x).numpy())
    assert np.count_nonzero(g) > 0.5 * g.size and np.all(g <= 0)   # more density: darker


def test_particle_density_gradients_match_finite_differences():
    """Per-particle densities (a Dr.Jit array with gradients) through capture -> exact / AVSM."""
    rng = np.random.default_rng(3)
    P = 6
    c = rng.uniform(-0.3, 0.3, (P, 3))
    r = rng.uniform(0.15, 0.3, P)
    s0 = rng.uniform(0.5, 3.0, P)
    rec = rng.uniform(-0.4, 0.4, (30, 3))
    w = rng.normal(size=rec.shape[0])

    for kind, params in (("exact", {}), ("avsm", {"nodes": 8})):
        def loss(sd):
            scene = Scene("p", DirectionalLight((0.3, -1.0, 0.2)), rec, particles=Particles(c, r, sd))
            cap = ad.capture(scene, resolution=64, dtype="float64", order="depth")
            T = cap.transmittance(ad.build(kind, cap.segments, **params), rec)
            return dr.sum(T * T64.Float64(w))

        chk = check_gradients(loss, T64.Float64(s0), fd=range(P), eps=EPS)
        assert chk.ok, (kind, chk)
        assert np.abs(chk.gradient).max() > 1e-3


# ----------------------------------------------------------------------------
# loop bounds: reverse vs forward mode on unequal segment counts
# ----------------------------------------------------------------------------
def _segments_loss(data, tex, depth, w, make):
    t = T64.Float64(data["tau"])
    dr.enable_grad(t)
    seg = ad.Segments.from_arrays(data["offsets"], data["z0"], data["z1"], optical_depth=t)
    return t, dr.sum(make(seg).eval(tex, depth) * T64.Float64(w))


def _unequal_counts(rng):
    """24 texels: empty ones, short ones (<= 12 segments) and two long ones (45, 30), with
    overlapping and zero-length segments."""
    counts = rng.integers(0, 13, 24)
    counts[[5, 17]] = 45, 30
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    n = int(offsets[-1])
    z0 = rng.uniform(0, 0.8, n)
    z1 = np.where(rng.random(n) < 0.1, z0, z0 + rng.uniform(0, 0.2, n))
    data = dict(offsets=offsets, z0=z0, z1=z1, tau=rng.exponential(0.08, n))
    tex = np.repeat(np.arange(24), 5)
    depth = rng.uniform(0, 1, tex.size)
    depth[np.isin(tex, [5, 17])] = 1.2                 # behind all of a long texel: every segment counts
    return data, tex, depth, rng.normal(size=tex.size)


LOOP_MODELS = {
    "exact": lambda s: ad.build("exact", s),
    "exact-checkpoint": lambda s: ad.build("exact", s, reverse="checkpoint"),
    "avsm": lambda s: ad.build("avsm", s, nodes=6),
    "avsm-checkpointed": lambda s: ad.build("avsm", s, nodes=6, reverse="checkpoint", chunk=7),
    "avsm-sorted": lambda s: ad.build("avsm", s, nodes=4, sort=True, interpolation="exp"),
    "avsm-sorted-checkpointed": lambda s: ad.build("avsm", s, nodes=4, sort=True, interpolation="exp",
                                                   reverse="checkpoint", chunk=5),
    "dsm-curve": lambda s: ad.build("dsm", s, tolerance=0.01, placement="curve"),
}


def _reverse_and_forward(data, tex, depth, w, make, v):
    t, L = _segments_loss(data, tex, depth, w, make)
    dr.backward(L)
    rev = dr.grad(t).numpy()
    t, L = _segments_loss(data, tex, depth, w, make)
    dr.set_grad(t, T64.Float64(v))
    dr.forward_to(L)
    return rev, dr.grad(L)[0], L[0]


@pytest.mark.parametrize("name", list(LOOP_MODELS))
def test_reverse_matches_forward_mode_with_unequal_counts(name):
    rng = np.random.default_rng(11)
    data, tex, depth, w = _unequal_counts(rng)
    v = rng.normal(size=data["tau"].size)
    rev, fwd, _ = _reverse_and_forward(data, tex, depth, w, LOOP_MODELS[name], v)
    np.testing.assert_allclose(fwd, rev @ v, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("plain, cheap", [("exact", "exact-checkpoint"), ("avsm", "avsm-checkpointed"),
                                          ("avsm-sorted", "avsm-sorted-checkpointed")])
def test_cheaper_reverse_paths_give_identical_gradients(plain, cheap):
    rng = np.random.default_rng(5)
    data, tex, depth, w = _unequal_counts(rng)
    v = rng.normal(size=data["tau"].size)
    r0, f0, l0 = _reverse_and_forward(data, tex, depth, w, LOOP_MODELS[plain], v)
    r1, f1, l1 = _reverse_and_forward(data, tex, depth, w, LOOP_MODELS[cheap], v)
    assert l0 == l1
    np.testing.assert_allclose(r1, r0, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(f1, f0, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("name", ["avsm", "avsm-sorted", "avsm-checkpointed"])
def test_too_small_loop_bound_is_refused(name, monkeypatch):
    """A ``max_iterations`` below the true iteration count (here: half the largest segment
    count) would make reverse mode write its per-lane trajectory past its end (stack
    corruption: segfaults later, in random test orders; JitFlag.Debug reports
    ``drjit.Local.write(): out-of-bounds write``) - the build refuses it before any kernel runs."""
    rng = np.random.default_rng(2)
    data, tex, depth, w = _unequal_counts(rng)
    true_max = int(np.diff(data["offsets"]).max())
    monkeypatch.setattr(ad.Segments, "max_count", property(lambda self: true_max // 2))
    with pytest.raises(ValueError, match="max_iterations"):
        _segments_loss(data, tex, depth, w, LOOP_MODELS[name])


_DEBUG_LOOPS = """
import sys
sys.path.insert(0, {tests!r})
import avsm_dr as ad
import drjit as dr
dr.set_flag(dr.JitFlag.Debug, True)
import numpy as np
import test_gradients_e2e as t
rng = np.random.default_rng(2)
data, tex, depth, w = t._unequal_counts(rng)
v = rng.normal(size=data["tau"].size)
for name in ("avsm", "avsm-sorted", "avsm-checkpointed"):
    t._reverse_and_forward(data, tex, depth, w, t.LOOP_MODELS[name], v)
true_max = int(np.diff(data["offsets"]).max())
ad.Segments.max_count = property(lambda self: true_max // 2)
try:
    t._reverse_and_forward(data, tex, depth, w, t.LOOP_MODELS["avsm"], v)
except ValueError as e:
    print("refused:", e)
"""


def test_reverse_loops_stay_in_bounds_under_jit_debug():
    """Under JitFlag.Debug (Dr.Jit's bounds checks; a subprocess, since the flag is
    global) reverse mode through the AVSM loops, right bound or too small, makes no
    out-of-bounds access: the too-small one is refused instead of overrunning the trajectory."""
    import pathlib
    import subprocess
    import sys
    tests = str(pathlib.Path(__file__).resolve().parent)
    proc = subprocess.run([sys.executable, "-c", _DEBUG_LOOPS.format(tests=tests)], capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "out-of-bounds" not in proc.stderr, proc.stderr[-3000:]
    assert "refused: max_iterations" in proc.stdout, proc.stdout


def test_exact_sum_loop_needs_no_bound(monkeypatch):
    """The exact curve's loop is a sum loop run with max_iterations=-1: reverse mode
    recomputes it, so even a wrong segment-count hint cannot change its gradients."""
    rng = np.random.default_rng(2)
    data, tex, depth, w = _unequal_counts(rng)
    v = rng.normal(size=data["tau"].size)
    rev_ok, fwd_ok, _ = _reverse_and_forward(data, tex, depth, w, LOOP_MODELS["exact"], v)
    np.testing.assert_allclose(rev_ok @ v, fwd_ok, rtol=1e-9)
    monkeypatch.setattr(ad.Segments, "max_count", property(lambda self: 1))
    rev_bad, _, _ = _reverse_and_forward(data, tex, depth, w, LOOP_MODELS["exact"], v)
    np.testing.assert_array_equal(rev_bad, rev_ok)


def test_checkpointed_loop_refuses_a_too_small_bound():
    rng = np.random.default_rng(4)
    data, tex, depth, w = _unequal_counts(rng)
    t = T64.Float64(data["tau"])
    dr.enable_grad(t)
    seg = ad.Segments.from_arrays(data["offsets"], data["z0"], data["z1"], optical_depth=t)
    UInt32 = T64.UInt32
    start = UInt32(data["offsets"][:-1].astype(np.uint32))
    end = UInt32(data["offsets"][1:].astype(np.uint32))

    def cond(p, i, acc):
        return i < end

    def body(p, i, acc):
        return i + 1, acc * 0.9 + dr.gather(T64.Float64, p[0], i)

    state = (start, dr.zeros(T64.Float64, 24))
    with pytest.raises(RuntimeError, match="max_iterations"):
        ck.checkpointed_while_loop(state, [seg.optical_depth], cond, body, seg.max_count - 1, chunk=4)
    out = ck.checkpointed_while_loop(state, [seg.optical_depth], cond, body, seg.max_count, chunk=4)
    dr.backward(dr.sum(out[1]))
    # d acc_texel / d tau_i = 0.9^(number of later segments in the texel)
    off = data["offsets"]
    ref = np.concatenate([0.9 ** np.arange(off[k + 1] - off[k] - 1, -1, -1) for k in range(24)])
    np.testing.assert_allclose(dr.grad(t).numpy(), ref, rtol=1e-12)


def test_checkpointed_avsm_handles_long_texels():
    """Thousands of segments per texel: the plain AVSM reverse pass keeps a trajectory of
    max_count x (2N + 5) words per lane on the worker stack (segfaults near 4000 segments
    for N = 8, see avsm_dr.representations._loops); the checkpointed one replays chunks of
    safe_chunk(2N + 5) iterations.  Gradient checked against forward mode."""
    rng = np.random.default_rng(9)
    T_, M = 4, 3000
    off = np.arange(T_ + 1) * M
    z0 = np.sort(rng.uniform(0, 1, (T_, M)), axis=1).ravel()
    data = dict(offsets=off, z0=z0, z1=z0 + 1e-3, tau=rng.uniform(0, 2.0 / M, T_ * M))
    tex, depth, w = np.arange(T_), np.full(T_, 0.7), rng.normal(size=T_)
    v = rng.normal(size=T_ * M)
    make = lambda s: ad.build("avsm", s, nodes=8)                     # noqa: E731  ('auto')
    rev, fwd, _ = _reverse_and_forward(data, tex, depth, w, make, v)
    np.testing.assert_allclose(fwd, rev @ v, rtol=1e-9)
    assert (2 * 8 + 5) * M > ck.TRAJECTORY_BUDGET_WORDS                      # trajectory words per lane
    t = T64.Float64(data["tau"])
    dr.enable_grad(t)
    seg = ad.Segments.from_arrays(off, z0, z0 + 1e-3, optical_depth=t)
    rep = ad.build("avsm", seg, nodes=8)
    assert rep.checkpoint_chunk() == ck.safe_chunk(rep.loop_state_words)       # 'auto' checkpoints
    # the explicit trajectory mode refuses what would overflow the worker stack (segfault)
    with pytest.raises(ValueError, match="reverse"):
        ad.build("avsm", seg, nodes=8, reverse="trajectory")


@pytest.mark.parametrize("kind", ["avsm"])  # exact: a sum loop, immune (test_exact_sum_loop_needs_no_bound)
def test_gradient_check_and_recover_refuse_a_too_small_bound(kind, monkeypatch):
    """The pipeline with a too-small loop bound patched in: gradient_check and recover()
    refuse it (ValueError) instead of running reverse mode past the trajectory."""
    rng = np.random.default_rng(6)
    scene, dens = _scene(rng)
    w = rng.normal(size=scene.receivers.shape[0])
    monkeypatch.setattr(ad.Segments, "max_count",
                        property(lambda self: max(1, int(self.counts.max()) // 2) if self.n_texels else 0))
    with pytest.raises(ValueError, match="max_iterations"):
        inv.gradient_check(lambda xt: _loss(scene, xt, kind, w, reverse="trajectory")[0], _tensor(dens))
    pts = scene.receivers
    tgt = np.asarray(inv.shadow(scene, dens, pts, kind="exact").T)
    with pytest.raises(ValueError, match="max_iterations"):
        inv.recover(scene, [scene.light], [tgt], [pts], kind=kind, params=None,
                    iterations=1, init="uniform", init_value=1.0, reverse="trajectory")


class _WrongReverse(dr.CustomOp):
    """Identity whose reverse mode doubles the gradient (forward mode is right): a
    reverse-only error, as a too-small loop bound would give without the refusal."""

    def eval(self, x):
        return x

    def forward(self):
        self.set_grad_out(self.grad_in("x"))

    def backward(self):
        self.set_grad_in("x", 2 * self.grad_out())


def test_gradient_check_and_recover_flag_a_reverse_mode_error(monkeypatch):
    """gradient_check reports a reverse-only error and recover() refuses to start."""
    rng = np.random.default_rng(6)
    scene, dens = _scene(rng)
    w = rng.normal(size=scene.receivers.shape[0])
    chk = inv.gradient_check(lambda xt: dr.custom(_WrongReverse, _loss(scene, xt, "avsm", w)[0]), _tensor(dens))
    assert not chk["ok"]
    pts = scene.receivers
    tgt = np.asarray(inv.shadow(scene, dens, pts, kind="exact").T)
    image_loss = inv.image_loss
    monkeypatch.setattr(inv, "image_loss", lambda p, t: dr.custom(_WrongReverse, image_loss(p, t)))
    with pytest.raises(RuntimeError, match="gradient check"):
        inv.recover(scene, [scene.light], [tgt], [pts], kind="avsm", params=None,
                    iterations=1, init="uniform", init_value=1.0)


def test_gradient_check_reports_agreement():
    rng = np.random.default_rng(6)
    scene, dens = _scene(rng)
    w = rng.normal(size=scene.receivers.shape[0])
    chk = inv.gradient_check(lambda xt: _loss(scene, xt, "avsm", w)[0], _tensor(dens), rtol=1e-9)
    assert chk["ok"] and chk["error"] <= 1e-9 * abs(chk["forward"]) + 1e-12


# ----------------------------------------------------------------------------
# inverse-problem building blocks
# ----------------------------------------------------------------------------
def test_projected_adam_matches_reference_formula():
    """drjit.opt.Adam's update (eps inside the square root, as Dr.Jit does for eps <= 1e-6)
    with the projection onto [0, inf) after each step, moments kept across projections."""
    F = T64.TensorXf64
    rng = np.random.default_rng(0)
    x0 = rng.uniform(0, 1, (2, 5, 5))
    grads = [rng.normal(size=x0.shape) for _ in range(3)]
    opt = inv.ProjectedAdam(lr=0.1, params={"sigma": F(x0)}, beta1=0.9, beta2=0.99, eps=1e-8)
    m = v = np.zeros(x0.shape)
    ref = x0.copy()
    for t_, g in enumerate(grads, start=1):
        x = opt["sigma"]
        dr.backward(dr.sum(x * F(g)).array)                            # dL/dx = g
        opt.step()
        m = 0.9 * m + 0.1 * g
        v = 0.99 * v + 0.01 * g * g
        ref = np.maximum(ref - 0.1 * math.sqrt(1 - 0.99 ** t_) / (1 - 0.9 ** t_) * m / np.sqrt(v + 1e-16), 0.0)
    np.testing.assert_allclose(opt["sigma"].numpy(), ref, rtol=1e-12, atol=1e-15)
    assert np.any(ref == 0.0)                                            # projection exercised


def test_receiver_grid_sits_behind_the_box_and_sees_full_optical_depth():
    rng = np.random.default_rng(8)
    scene, dens = _scene(rng)
    light = DirectionalLight((0.2, -0.5, 1.0))
    pts = inv.receiver_grid(scene.bbox, light, 6)
    corners = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (0.0, 1.2) for z in (-0.5, 0.5)])
    assert np.all(pts @ light.direction > (corners @ light.direction).max())
    T = np.asarray(inv.shadow(scene, dens, pts, light=light, kind="exact", epsilon=1e-12).T)
    for kind in ("fom", "osm", "avsm"):                   # behind everything: exact for all of them
        Tk = np.asarray(inv.shadow(scene, dens, pts, light=light, kind=kind, epsilon=1e-12).T)
        np.testing.assert_allclose(Tk, T, atol=2e-5)       # float32 capture: rounding of sum tau
    assert T.min() < 0.5


def test_radiance_matches_shading_and_is_differentiable():
    """L = albedo / pi * E * cos * T as in shading.shade_receivers, with d L / d T = weights."""
    from avsm_dr import shading
    rng = np.random.default_rng(10)
    scene, dens = _scene(rng)
    light = DirectionalLight((0.2, -0.5, 1.0), irradiance=3.0)
    pts = inv.receiver_grid(scene.bbox, light, 5)
    normal = np.array([0.3, 0.5, -1.0])
    wts = inv.radiance_weights(light, pts, normal=normal, albedo=0.7)
    x = _tensor(dens, grad=True)
    T = inv.shadow(scene, x, pts, light=light, kind="fom").T
    Lo = inv.radiance(T, wts)
    ref = shading.shade_receivers(inv.with_light(scene, light), np.asarray(T), pts, normals=normal, albedo=0.7)
    np.testing.assert_allclose(np.asarray(Lo), ref, rtol=1e-12)
    dr.backward(dr.sum(Lo))
    assert np.abs(dr.grad(x).numpy()).max() > 0


def test_recover_reduces_loss_and_density_error():
    """A few Adam steps from an empty grid (plume, 2 lights): the shadow loss falls by 10x
    and the density error below its start (1.0); reverse and forward mode agree."""
    scene = ad.scenes.plume(size=6, density_scale=20.0)
    lights = [inv.light_from_angles(a, 20) for a in (180, 300)]
    recs = [inv.receiver_grid(scene.bbox, l, 12) for l in lights]
    tg = [np.asarray(inv.shadow(scene, scene.density, r, light=l, kind="exact").T) for l, r in zip(lights, recs)]
    out = inv.recover(scene, lights, tg, recs, kind="fom", iterations=12, lr=0.5, truth=scene.density)
    h = out.history
    assert out.gradient_check["ok"]
    assert h[-1]["data"] < 0.1 * h[0]["data"]
    assert h[0]["density_rel_l2"] == 1.0 and h[-1]["density_rel_l2"] < 0.9
    assert out.density.min() >= 0


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["fom", "avsm"])
def test_recover_plume_three_lights(kind):
    scene = ad.scenes.plume(size=8, density_scale=20.0)
    lights = [inv.light_from_angles(a, 20) for a in (180, 300, 60)]
    recs = [inv.receiver_grid(scene.bbox, l, 20) for l in lights]
    tg = [np.asarray(inv.shadow(scene, scene.density, r, light=l, kind="exact").T) for l, r in zip(lights, recs)]
    out = inv.recover(scene, lights, tg, recs, kind=kind, iterations=60, lr=0.5, truth=scene.density)
    assert out.history[-1]["data"] < 0.01 * out.history[0]["data"]
    assert out.history[-1]["density_rel_l2"] < 0.5


@pytest.mark.parametrize("call, name", [
    (lambda s, d: inv.shadow(s, d, kind="nope"), "kind"),
    (lambda s, d: inv.shadow(s, d, kind="dsm", params={"tolerance": 0.01}), "params"),
    (lambda s, d: inv.shadow(s, -d, kind="fom"), "density"),
    (lambda s, d: inv.recover(s, [s.light], [np.ones(3)], [np.zeros((3, 3))], init="random"), "init"),
    (lambda s, d: inv.recover(s, [s.light], [], [np.zeros((3, 3))]), "targets"),
    (lambda s, d: inv.density_error(d, d[:-1]), "recovered"),
    (lambda s, d: inv.receiver_grid(s.bbox, s.light, 0), "n"),
    (lambda s, d: inv.ProjectedAdam(lr=0.0), "lr"),
    (lambda s, d: inv.ProjectedAdam(beta2=1.0), "beta2"),
    (lambda s, d: ck.checkpointed_while_loop((), [], None, None, 3, chunk=0), "chunk"),
])
def test_bad_input_raises_value_error(call, name):
    scene, dens = _scene(np.random.default_rng(0))
    with pytest.raises(ValueError, match=name):
        call(scene, dens)
