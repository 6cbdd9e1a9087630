"""avsm_dr.validation: one rule for numbers, vectors and points."""
import numpy as np
import pytest

import avsm_dr  # noqa: F401  (libLLVM before drjit)
from avsm_dr import validation as V


@pytest.mark.parametrize("value", [2, 2.5, np.float32(2.5), np.float64(2.5), np.int64(2), np.uint8(2)])
def test_real_accepts_python_and_numpy_scalars(value):
    assert V.real(value, "x") == float(value)
    assert type(V.real(value, "x")) is float


@pytest.mark.parametrize("value", [True, np.bool_(False), "2", b"2", np.array([2.0]), np.array(2.0),
                                   [2.0], None, float("nan"), float("inf"), -float("inf"), 1 + 0j])
def test_real_refuses_everything_else(value):
    with pytest.raises(ValueError, match=r"^far: expected a finite real number"):
        V.real(value, "far")


def test_real_range_and_infinity():
    assert V.real(0.0, "x", 0.0) == 0.0
    with pytest.raises(ValueError, match=r"^x: expected a finite real number > 0, got 0.0"):
        V.real(0.0, "x", 0.0, open_min=True)
    with pytest.raises(ValueError, match=r"^x: .* in \[0, 1\], got 1.5"):
        V.real(1.5, "x", 0.0, 1.0)
    assert V.real(float("inf"), "x", 0.0, finite=False) == float("inf")
    with pytest.raises(ValueError, match="not NaN"):
        V.real(float("nan"), "x", finite=False)


@pytest.mark.parametrize("value", [3, np.int32(3), np.uint64(3)])
def test_integer_accepts_integral_scalars(value):
    assert V.integer(value, "n", 1) == 3


@pytest.mark.parametrize("value", [True, False, 3.0, np.float64(3.0), "3", np.array([3]), None])
def test_integer_refuses_bool_float_str_arrays(value):
    with pytest.raises(ValueError, match=r"^n: expected an integer"):
        V.integer(value, "n")


def test_integer_range_message_prints_integers():
    with pytest.raises(ValueError, match=r"^n: expected an integer in \[1, 4194304\], got 0$"):
        V.integer(0, "n", 1, 1 << 22)


def test_vec3_and_unit_vector():
    np.testing.assert_array_equal(V.vec3([1, 2, 3], "v"), [1.0, 2.0, 3.0])
    for bad in ([1, 2], ["1", "2", "3"], [1, 2, np.nan], [True, False, True], "abc", [[1, 2], [3]]):
        with pytest.raises(ValueError, match="^v: expected 3 finite numbers"):
            V.vec3(bad, "v")
    # norms that overflow or underflow float64 still normalise (scaled by the largest entry)
    np.testing.assert_allclose(V.unit_vector([1e300, 1e300, 0], "d"), [2 ** -0.5, 2 ** -0.5, 0], rtol=1e-15)
    np.testing.assert_array_equal(V.unit_vector([1e-320, 0, 0], "d"), [1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="^d: must be non-zero"):
        V.unit_vector([0, 0, 0], "d")


def test_array_refuses_bool_and_strings_and_dtype_overflow():
    with pytest.raises(ValueError, match="^a: expected a numeric array, got dtype bool"):
        V.array([True, False], "a")
    with pytest.raises(ValueError, match="^a: expected a numeric array"):
        V.array(["1.0"], "a")
    with pytest.raises(ValueError, match="^a: contains 1 NaN or inf"):
        V.array([1.0, np.inf], "a")
    # finite in float64 but not in float32 storage
    with pytest.raises(ValueError, match="^a: values beyond the float32 range"):
        V.array([1e39], "a", np.float32)
    assert V.array([1.0, np.inf], "a", finite=False)[1] == np.inf


def test_points():
    assert V.points([1, 2, 3]).shape == (1, 3)
    assert V.points(np.zeros((0, 3)), allow_empty=True).shape == (0, 3)
    with pytest.raises(ValueError, match="^points: no points given"):
        V.points(np.zeros((0, 3)))
    with pytest.raises(ValueError, match=r"^receivers: expected shape \(K, 3\)"):
        V.points(np.zeros((4, 2)), "receivers")
    with pytest.raises(ValueError, match="^points: contains 1 NaN"):
        V.points([[0, np.nan, 0]])


# ------------------------------------------------------------------ density grids
def _grid_entry_points():
    """Every public entry point that takes a density grid, as ``grid -> call``."""
    import avsm_dr as ad
    from avsm_dr import fluid, groundtruth as gt, reconstruction
    from avsm_dr.capture.grid import GridVolume
    from avsm_dr.scene import DirectionalLight, Scene
    box, light = (np.zeros(3), np.ones(3)), DirectionalLight((0.2, -1.0, 0.1))
    ok = np.ones((4, 4, 4), np.float32)
    scene = Scene("grid", light, np.full((1, 3), 0.5), density=ok, bbox=box)
    return {
        "Scene": lambda g: Scene("grid", light, np.full((1, 3), 0.5), density=g, bbox=box),
        "GridVolume.prepare": lambda g: GridVolume.prepare(g, box),
        "capture(density=)": lambda g: ad.capture(scene, resolution=64, density=g),
        "sample_density": lambda g: gt.sample_density(g, box, np.full((1, 3), 0.5)),
        "raymarch_optical_depth": lambda g: gt.raymarch_optical_depth(g, box, [[0.5, 2, 0.5]], [[0, -1, 0]], [3.0]),
        "mitsuba_volume": lambda g: gt.mitsuba_volume(g, box),
        "StableFluids.set_density": lambda g: fluid.StableFluids((4, 4, 4)).set_density(g),
        "density_tensor": lambda g: reconstruction.density_tensor(g),
    }


def _int_grids():
    import drjit as dr
    g = np.arange(64).reshape(4, 4, 4)
    return {"uint8": g.astype(np.uint8), "int64": g, "bool": g > 30, "list_of_ints": g.tolist(),
            "drjit_int": dr.llvm.ad.TensorXi(g.astype(np.int32))}


@pytest.mark.parametrize("entry", list(_grid_entry_points()))
@pytest.mark.parametrize("grid", list(_int_grids()))
def test_integer_and_bool_grids_are_refused_everywhere(entry, grid):
    """uint8 voxels 0..255 were read as extinction 0..255 per unit; every entry point now
    refuses non-float grids by one rule, naming the argument and the conversion."""
    if entry == "mitsuba_volume":
        pytest.importorskip("mitsuba")
    with pytest.raises(ValueError, match=r"^density: (integer|boolean) grid \(dtype \w+\) refused: .*"
                                         r"convert it with an explicit scale"):
        _grid_entry_points()[entry](_int_grids()[grid])


@pytest.mark.parametrize("entry", list(_grid_entry_points()))
def test_float_grids_still_pass_every_entry_point(entry):
    if entry == "mitsuba_volume":
        pytest.importorskip("mitsuba")
    for g in (np.ones((4, 4, 4), np.float32), np.ones((4, 4, 4)), np.ones((4, 4, 4), np.float16)):
        _grid_entry_points()[entry](g)


@pytest.mark.parametrize("bad, msg", [(np.full((2, 2, 2), np.nan), "contains 8 NaN or inf"),
                                      (np.full((2, 2, 2), -1.0), "negative extinction -1"),
                                      (np.full((2, 2, 2), 1e300), "values beyond the float32 range"),
                                      (np.ones((2, 2)), r"expected a 3-D \(z, y, x\) array"),
                                      (np.ones((0, 2, 2)), "empty grid"),
                                      (np.array([[["a"]]]), "expected a floating-point")])
def test_density_grid_rule(bad, msg):
    with pytest.raises(ValueError, match="^density: " + msg):
        V.density_grid(bad)


def test_corrupt_plume_cache_is_named_and_recomputed(tmp_path):
    """The fluid's ``.npy`` cache is read without pickles and checked (dtype, shape, values):
    a wrong file is warned about by name and recomputed."""
    from avsm_dr import fluid
    kw = dict(shape=(4, 6, 4), steps=1, cache=tmp_path)
    good = fluid.simulate_plume(**kw)
    (path,) = tmp_path.glob("plume_*.npy")
    for bad in (np.zeros((4, 6, 4), np.uint8), np.zeros((2, 2, 2), np.float32), np.array([print], object)):
        np.save(path, bad, allow_pickle=True)
        with pytest.warns(RuntimeWarning, match=f"ignoring the cached plume '{path}'"):
            again = fluid.simulate_plume(**kw)
        assert again.dtype == np.float32 and np.array_equal(again, good)
    path.write_bytes(b"garbage")
    with pytest.warns(RuntimeWarning, match="ignoring the cached plume"):
        assert np.array_equal(fluid.simulate_plume(**kw), good)
