"""Insertion order of the capture (``ad.capture(..., order=...)``, ``Segments.order``): every
order holds the same segments per texel, each is the order it says (depth, reverse depth, a
seeded shuffle, a renderer's draw order) against NumPy references, it is recorded and kept,
sorted AVSM does not depend on it, and bad values are refused naming the argument."""
from __future__ import annotations

import inspect
import subprocess
import sys

import numpy as np
import pytest

import avsm_dr as ad
import drjit as dr
from avsm_dr import texel_sort as TS
from avsm_dr.capture import ORDERS
from avsm_dr.capture import GridVolume
from avsm_dr.capture._grid_lanes import SUBMISSION_BRICK
from avsm_dr.scene import DirectionalLight, Hair, OpaqueSphere, Particles, Scene, SpotLight
from avsm_dr.segments import OPAQUE_OPTICAL_DEPTH, Segments

RES = 64
#: Built-in scenes covering every content kind: grid, particles, grid + hair, grid + blockers.
SCENES = ("plume", "particles", "hair_and_smoke", "smoke_over_table")
#: (order, extra capture arguments) of every order the capture makes.
VARIANTS = (("depth", {}), ("reverse_depth", {}), ("random", {"order_seed": 7}), ("submission", {}),
            ("submission", {"submission": "back_to_front"}))


def _texels(seg):
    """Host arrays and, per segment, its texel and rank inside the texel."""
    h = seg.numpy()
    tex = np.repeat(np.arange(seg.n_texels), seg.counts)
    return h, tex, np.arange(tex.size) - h["offsets"][tex]


def _per_texel_sorted(seg) -> np.ndarray:
    """(S, 3) rows (z0, z1, tau) sorted inside every texel: the texel's multiset."""
    h, tex, _ = _texels(seg)
    rows = np.stack([h["z0"], h["z1"], h["optical_depth"]], 1)
    return rows[np.lexsort((rows[:, 2], rows[:, 1], rows[:, 0], tex))]


@pytest.fixture(scope="module")
def captures():
    """{(scene, order, submission): Segments} of every built-in content kind at 64^2."""
    out = {}
    for name in SCENES:
        sc = ad.scenes.get(name)
        for order, kw in VARIANTS:
            out[name, order, kw.get("submission")] = ad.capture(sc, resolution=RES, order=order, **kw).segments
    return out


# --------------------------------------------------------------------------- all orders
@pytest.mark.parametrize("name", SCENES)
def test_every_order_holds_the_depth_orders_segments(captures, name):
    ref = captures[name, "depth", None]
    want = _per_texel_sorted(ref)
    for (n, order, sub), seg in captures.items():
        if n != name:
            continue
        assert seg.order == order and np.array_equal(seg.offsets, ref.offsets), (order, sub)
        assert np.array_equal(_per_texel_sorted(seg), want), (order, sub)


@pytest.mark.parametrize("name", SCENES)
def test_depth_is_front_to_back_and_reverse_is_its_reversal(captures, name):
    d, r = captures[name, "depth", None], captures[name, "reverse_depth", None]
    hd, tex, rank = _texels(d)
    hr = r.numpy()
    same = np.diff(tex) == 0
    assert np.all(np.diff(hd["z0"])[same] >= 0) and d.sorted_by_depth
    assert np.all(np.diff(hr["z0"])[same] <= 0) and not r.sorted_by_depth
    src = hd["offsets"][tex + 1] - 1 - rank                 # slot r <- slot count - 1 - r
    for k in ("z0", "z1", "optical_depth"):
        assert np.array_equal(hr[k], hd[k][src])


def test_hair_alone_is_sorted_by_depth():
    """Regression: a capture with one host piece in texel order (hair alone: by texel, then
    strand) skipped the depth sort yet was flagged sorted (462 inversions at 64^2)."""
    hs = ad.scenes.get("hair_and_smoke")
    sc = Scene("hair", hs.light, hs.receivers, hair=hs.hair)
    seg = ad.capture(sc, resolution=RES, order="depth").segments
    h, tex, _ = _texels(seg)
    assert seg.sorted_by_depth and np.all(np.diff(h["z0"])[np.diff(tex) == 0] >= 0)
    # sorted and unsorted AVSM builds of sorted input are the same (avsm module docstring)
    a, b = ad.build("avsm", seg, nodes=4), ad.build("avsm", seg, nodes=4, sort=True)
    assert all(np.array_equal(x.numpy(), y.numpy()) for x, y in zip(a.depths + a.values, b.depths + b.values))


# ------------------------------------------------------------------------------ random
def _random_reference(depth_seg, seed):
    """The 'random' order from the depth order in NumPy: per texel by (shuffle_key, rank)."""
    h, tex, rank = _texels(depth_seg)
    mix = [np.uint32(m) for m in TS._MIX]
    with np.errstate(over="ignore"):                # texel_sort.shuffle_key's hash, in NumPy
        s = TS._mix32(np.array([seed], np.uint32), *mix)[0]
        key = TS._mix32(TS._mix32(tex.astype(np.uint32) + s, *mix) + rank.astype(np.uint32), *mix)
    perm = np.lexsort((rank, key, tex))
    return {k: h[k][perm] for k in ("z0", "z1", "optical_depth")}


def test_random_matches_the_numpy_reference_and_its_seed(captures):
    sc = ad.scenes.get("hair_and_smoke")
    depth = captures["hair_and_smoke", "depth", None]
    assert depth.max_count >= 3
    got = captures["hair_and_smoke", "random", None]
    ref = _random_reference(depth, 7)
    assert all(np.array_equal(got.numpy()[k], ref[k]) for k in ref)
    again = ad.capture(sc, resolution=RES, order="random", order_seed=7).segments.numpy()
    other = ad.capture(sc, resolution=RES, order="random", order_seed=8).segments.numpy()
    assert np.array_equal(again["z0"], got.numpy()["z0"])
    assert not np.array_equal(other["z0"], again["z0"])
    assert np.array_equal(other["z0"], _random_reference(depth, 8)["z0"])
    # the default seed is 0
    zero = ad.capture(sc, resolution=RES, order="random").segments.numpy()["z0"]
    assert np.array_equal(zero, _random_reference(depth, 0)["z0"])
    assert np.array_equal(depth.in_order("random", seed=7).numpy()["z0"], ref["z0"])


def test_random_is_independent_of_the_thread_count():
    """The shuffle's keys depend on (seed, texel, rank) only: one worker thread and the
    default pool give the same order (a fresh process, the pool size fixed at start)."""
    code = ("import avsm_dr as ad, drjit as dr, numpy as np, sys\n"
            "n = int(sys.argv[1])\n"
            "dr.set_thread_count(n) if n else None\n"
            "seg = ad.capture(ad.scenes.get('particles'), resolution=64, order='random', order_seed=5).segments\n"
            "print(np.asarray(seg.numpy()['z0'], np.float64).round(9).tobytes().hex()[:4000], seg.n_segments)\n")
    out = [subprocess.run([sys.executable, "-c", code, str(n)], capture_output=True, text=True, timeout=300)
           for n in (1, 0)]
    assert all(o.returncode == 0 for o in out), [o.stderr[-2000:] for o in out]
    assert out[0].stdout == out[1].stdout


# -------------------------------------------------------------------------- submission
def _particle_scene(order_of_list):
    """Three particles stacked under a light pointing down (-y): depth grows as y falls."""
    ys = {"near": 0.5, "mid": 0.0, "far": -0.5}
    c = np.array([[0.0, ys[k], 0.0] for k in order_of_list])
    return Scene("stack", DirectionalLight((0.0, -1.0, 0.0)), np.zeros((1, 3)),
                 particles=Particles(centers=c, radii=np.full(3, 0.2), density=np.full(3, 2.0)))


@pytest.mark.parametrize("light", ["directional", "spot"])
def test_submission_draws_particles_in_list_or_back_to_front_order(light):
    sc = _particle_scene(["mid", "far", "near"])
    if light == "spot":
        sc = Scene(sc.name, SpotLight((0.0, 2.0, 0.0), (0.0, -1.0, 0.0), 30.0), sc.receivers, particles=sc.particles)
    depth_of = {}                                   # chord midpoint -> particle, by its centre's depth
    cases = {"list": ["mid", "far", "near"], "back_to_front": ["far", "mid", "near"]}
    for sub, want in cases.items():
        seg = ad.capture(sc, resolution=RES, submission=sub).segments          # the default order
        assert seg.order == "submission"
        h, tex, _ = _texels(seg)
        full = np.flatnonzero(seg.counts == 3)
        assert full.size > 20
        for t in full:
            s = slice(h["offsets"][t], h["offsets"][t + 1])
            mids = 0.5 * (h["z0"][s] + h["z1"][s])
            names = np.array(["near", "mid", "far"])[np.argsort(np.argsort(mids))]   # by depth
            assert list(names) == want, (sub, t)
        depth_of[sub] = seg
    d = ad.capture(sc, resolution=RES, order="depth").segments
    assert np.array_equal(_per_texel_sorted(d), _per_texel_sorted(depth_of["list"]))


def test_submission_draws_strands_in_list_and_vertex_order():
    """Light along +x.  Strand A, a U whose vertices start on its far leg (x = +0.2), then
    strand B, a vertical line nearer (x = -0.5): a ray through all three legs meets A's far
    leg, A's near leg, then B in draw order, but B, A-near, A-far in depth."""
    y = np.linspace(0.3, -0.3, 7)
    far_leg = np.stack([np.full(7, 0.2), y, np.zeros(7)], 1)
    near_leg = np.stack([np.full(7, -0.2), y[::-1], np.zeros(7)], 1)
    bottom = np.stack([np.linspace(0.2, -0.2, 7), np.full(7, -0.3), np.zeros(7)], 1)
    a = np.concatenate([far_leg, bottom[1:], near_leg[1:]])                 # 19 vertices
    b = np.stack([np.full(19, -0.5), np.linspace(-0.3, 0.3, 19), np.zeros(19)], 1)
    sc = Scene("u", DirectionalLight((1.0, 0.0, 0.0)), np.zeros((1, 3)),
               hair=Hair(strands=np.stack([a, b]), radius=0.01, opacity=0.3))
    sub = ad.capture(sc, resolution=RES, order="submission").segments
    dep = ad.capture(sc, resolution=RES, order="depth").segments
    hs, tex, _ = _texels(sub)
    hd = dep.numpy()
    three = np.flatnonzero(sub.counts == 3)
    assert three.size > 0
    for t in three:
        s = slice(hs["offsets"][t], hs["offsets"][t + 1])
        assert np.all(np.diff(hs["z0"][s]) < 0)                    # far leg, near leg, B
        assert np.array_equal(hs["z0"][s], hd["z0"][s][::-1])


def _brick_reference(cap, grid):
    """The submission order of a grid alone in NumPy: the depth order stably sorted, per texel,
    by the brick (x fastest) holding each segment's midpoint."""
    h, tex, _ = _texels(cap.segments)
    o, d = cap.camera.rays(tex)
    p = o + (0.5 * (h["z0"] + h["z1"]))[:, None] * d
    nb = -(-np.array(grid.shape[::-1]) // SUBMISSION_BRICK)
    b = np.clip(np.floor((p - grid.bmin) / (grid.voxel * SUBMISSION_BRICK)), 0, nb - 1).astype(np.int64)
    key = (b[:, 2] * nb[1] + b[:, 1]) * nb[0] + b[:, 0]
    perm = np.lexsort((np.arange(tex.size), key, tex))
    return key[perm], {k: h[k][perm] for k in ("z0", "z1", "optical_depth")}


@pytest.mark.parametrize("method", ["march", "exact"])
def test_submission_draws_grid_bricks_in_memory_order(method):
    rng = np.random.default_rng(3)
    dens = (rng.random((20, 24, 28)) * 4).astype(np.float32)
    bbox = (np.array([-1.0, -0.8, -0.7]), np.array([1.0, 0.8, 0.7]))
    sc = Scene("bricks", DirectionalLight((1.0, -0.7, 0.4)), np.zeros((1, 3)), density=dens, bbox=bbox)
    depth = ad.capture(sc, resolution=RES, order="depth", method=method)
    sub = ad.capture(sc, resolution=RES, order="submission", method=method)
    key, ref = _brick_reference(depth, GridVolume.prepare(dens, bbox))
    got = sub.segments.numpy()
    assert all(np.array_equal(got[k], ref[k]) for k in ref)
    _, tex, _ = _texels(sub.segments)
    same = np.diff(tex) == 0
    assert np.all(np.diff(key)[same] >= 0)                          # bricks in memory order
    in_brick = same & (np.diff(key) == 0)
    assert np.all(np.diff(got["z0"])[in_brick] > 0)                 # a brick's stretch front to back
    assert np.any(np.diff(got["z0"])[same] < 0)                     # and not the depth order


@pytest.mark.parametrize("opaque", ["inline", "separate"])
def test_submission_puts_blockers_first_in_list_order(opaque):
    base = ad.scenes.get("plume")
    spheres = [OpaqueSphere((0.0, -0.55, 0.0), 0.08), OpaqueSphere((0.05, 0.9, 0.0), 0.08)]
    sc = Scene("blocked", DirectionalLight((0.0, -1.0, 0.0)), base.receivers, density=base.density,
               bbox=base.bbox, blockers=spheres)
    cap = ad.capture(sc, resolution=RES, order="submission", opaque=opaque)
    dep = ad.capture(sc, resolution=RES, order="depth", opaque=opaque)
    assert np.array_equal(_per_texel_sorted(cap.segments), _per_texel_sorted(dep.segments))
    h, tex, rank = _texels(cap.segments)
    opq = h["optical_depth"] >= OPAQUE_OPTICAL_DEPTH
    if opaque == "separate":
        assert not opq.any() and np.isfinite(cap.opaque_depth).any()
        return
    both = np.flatnonzero(np.bincount(tex[opq], minlength=cap.segments.n_texels) == 2)
    assert both.size > 0 and np.all(rank[opq] < 2)                 # first in their texel, ...
    for t in both:                                                  # ... blocker 0 (below) first
        z = h["z0"][h["offsets"][t]:h["offsets"][t] + 2]
        assert z[0] > z[1]


# ------------------------------------------------------------------- sorted AVSM, label
def _nodes(rep):
    return np.stack([a.numpy() for a in rep.depths + rep.values])


@pytest.mark.parametrize("name", SCENES)
def test_sorted_avsm_is_the_same_in_every_capture_order(captures, name):
    ref = ad.build("avsm", captures[name, "depth", None], nodes=8)
    want = _nodes(ref)
    assert np.array_equal(_nodes(ad.build("avsm", captures[name, "depth", None], nodes=8, sort=True)), want)
    differs = False
    for (n, order, sub), seg in captures.items():
        if n == name and order != "depth":
            assert np.array_equal(_nodes(ad.build("avsm", seg, nodes=8, sort=True)), want), (order, sub)
            differs |= not np.array_equal(_nodes(ad.build("avsm", seg, nodes=8)), want)
    assert differs                                                  # unsorted AVSM depends on it


def test_order_is_recorded_and_kept():
    seg = ad.Segments.from_arrays([0, 2, 3], [0.5, 0.1, 0.2], [0.6, 0.3, 0.4], optical_depth=[1.0, 2.0, 0.5])
    assert seg.order == "unknown" and seg.sorted().order == "depth"
    assert ad.Segments.from_arrays([0, 1], [0.0], [1.0], optical_depth=[1.0], order="random").order == "random"
    rev = seg.in_order("reverse_depth")
    assert rev.order == "reverse_depth" and rev.numpy()["z0"].tolist() == pytest.approx([0.5, 0.1, 0.2])
    assert rev.select_texels([1, 0]).order == "reverse_depth"
    assert seg.in_order("depth").numpy()["z0"].tolist() == pytest.approx([0.1, 0.5, 0.2])
    assert "order=reverse_depth" in repr(rev)
    cap = ad.capture(ad.scenes.get("particles"), resolution=RES)
    assert cap.order == cap.segments.order == "submission"           # the default: a renderer's order
    assert inspect.signature(ad.capture).parameters["order"].default == "submission" == ORDERS[0]
    assert cap.stats["order"] == {"order": "submission", "submission": "list"}
    assert cap.segments.select_texels([0, 5]).order == "submission"
    empty = Segments(np.zeros(3, np.int64), *(ad.backend.types().Float() for _ in range(3)), sorted_by_depth=True)
    assert empty.order == "depth"


def test_gradients_follow_the_order():
    """Per-particle densities with gradients: d(sum of tau * weight)/d density is the same
    whatever the order, when the weight follows each segment (its z0)."""
    Float = ad.backend.types().Float
    base = _particle_scene(["mid", "far", "near"])
    grads = []
    for order in ("depth", "random", "submission"):
        dens = Float(2.0, 3.0, 4.0)
        dr.enable_grad(dens)
        p = base.particles
        sc = Scene(base.name, base.light, base.receivers,
                   particles=Particles(centers=p.centers, radii=p.radii, density=dens))
        seg = ad.capture(sc, resolution=RES, order=order).segments
        dr.backward(dr.sum(seg.optical_depth * dr.detach(seg.z0)))
        grads.append(dens.grad.numpy())
    assert np.allclose(grads[0], grads[1], rtol=1e-5) and np.allclose(grads[0], grads[2], rtol=1e-5)  # float32 sums


@pytest.mark.parametrize("kwargs, name", [
    (dict(order="front_to_back"), "order"), (dict(order=None), "order"),
    (dict(order="submission", submission="sorted"), "submission"),
    (dict(order="depth", submission="list"), "submission"),
    (dict(order="depth", order_seed=1), "order_seed"),
    (dict(order="random", order_seed=-1), "order_seed"),
    (dict(order="random", order_seed=2**32), "order_seed"),
])
def test_bad_order_arguments_name_the_argument(kwargs, name):
    with pytest.raises(ValueError, match=rf"^{name}: "):
        ad.capture(ad.scenes.get("particles"), resolution=RES, **kwargs)


def test_bad_segment_orders_name_the_argument():
    seg = ad.Segments.from_arrays([0, 1], [0.0], [1.0], optical_depth=[1.0])
    with pytest.raises(ValueError, match=r"^order: "):
        seg.in_order("submission")
    with pytest.raises(ValueError, match=r"^order: "):
        ad.Segments.from_arrays([0, 1], [0.0], [1.0], optical_depth=[1.0], order="sorted")
    with pytest.raises(ValueError, match=r"^seed: "):
        seg.in_order("depth", seed=3)
    with pytest.raises(ValueError, match=r"^seed: "):
        seg.in_order("random", seed=1.5)
