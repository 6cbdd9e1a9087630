"""One depth-range rule for every kind with ``near``/``far`` (representations/base.py,
:func:`~avsm_dr.representations.base.depth_range`): an explicit range must contain every
segment; one that cuts the content is refused with a ValueError naming the argument at
fault (``near``, ``far`` or both), its value and the content's span.

Registry-driven: every kind whose schema has ``near`` and ``far`` is parametrised, so a new
kind is covered without editing this file.  With segments [0.1, 0.3]
(T 0.5) and [0.35, 0.5] (T 0.7), ``near=0.3, far=0.45``, FOM returned 0.659 / 0.612 /
0.394 at depths 0.32 / 0.4 / 0.48 (exact 0.5 / 0.444 / 0.367), while AVSM refused it
naming ``far`` for a ``near`` at fault.
"""
from __future__ import annotations

import re

import numpy as np
import pytest

import avsm_dr as ad

RANGE_KINDS = [k for k in ad.kinds() if {"near", "far"} <= set(ad.describe(k)["params"])]
DTYPES = ["float32", "float64"]


def test_every_kind_with_a_depth_range_is_covered():
    """The kinds whose depth range once went wrong are among the parametrised ones (the list is not empty)."""
    assert {"avsm", "avsm_adaptive", "basis", "fom", "moments", "osm"} <= set(RANGE_KINDS)


def _issue_segments(dtype):
    """One texel: [0.1, 0.3] with T 0.5, [0.35, 0.5] with T 0.7 (the issue's example)."""
    return ad.Segments.from_arrays([0, 2], [0.1, 0.35], [0.3, 0.5], transmittance=[0.5, 0.7], dtype=dtype)


#: (near, far, the arguments at fault): the issue's example and its mirrored cases.
CUTS = [
    (0.3, 0.45, ("near", "far")),        # the issue: cuts both ends
    (0.3, None, ("near",)),              # far defaults to the content's end
    (0.3, 0.5, ("near",)),
    (0.15, 0.6, ("near",)),
    (None, 0.45, ("far",)),              # near defaults to the content's start
    (0.1, 0.45, ("far",)),
    (0.0, 0.4, ("far",)),
    (0.2, 0.3, ("near", "far")),
    (0.6, 0.9, ("near",)),               # wholly behind the content (far contains its end)
    (-0.5, 0.05, ("far",)),              # wholly in front of it
]


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("near, far, fault", CUTS, ids=lambda v: repr(v))
@pytest.mark.parametrize("kind", RANGE_KINDS)
def test_range_cutting_the_content_is_refused(kind, near, far, fault, dtype):
    seg = _issue_segments(dtype)
    given = {k: v for k, v in (("near", near), ("far", far)) if v is not None}
    with pytest.raises(ValueError) as info:
        ad.build(kind, seg, **given)
    msg = str(info.value)
    assert msg.startswith(f"{fault[0]}:"), msg
    for name in ("near", "far"):
        named = re.search(rf"\b{name}: ", msg) is not None
        assert named == (name in fault), (name, msg)
        if name in fault:
            assert f"{name}: {given[name]!r}" in msg, msg          # the offending value
    assert "[0.1, 0.5]" in msg, msg                                  # the content's span


#: Explicit ranges that contain the content: tight (the stored bounds, also given as the
#: float64 literals 0.1 / 0.5, which round to the float32 bounds) and loose.
CONTAINING = [(0.1, 0.5), (0.0, 1.0), (0.1, None), (None, 0.5), (-2.0, 3.0)]


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("near, far", CONTAINING)
@pytest.mark.parametrize("kind", RANGE_KINDS)
def test_range_containing_the_content_is_accepted(kind, near, far, dtype):
    """Accepted, T in [0, 1], T = 1 in front of the content, and T behind far equal to the
    exact total transmittance 0.35 to float rounding of the sum (every kind stores it:
    node kinds as their last node, basis kinds as T(u = 1) = exp(-total tau))."""
    seg = _issue_segments(dtype)
    given = {k: v for k, v in (("near", near), ("far", far)) if v is not None}
    rep = ad.build(kind, seg, **given)
    T = np.asarray(rep.eval([0, 0, 0], [-5.0, 0.4, 5.0]), np.float64)
    assert np.all((T >= 0) & (T <= 1)), T
    if rep.unity_in_front:
        assert T[0] == 1.0
    tol = 1e-6 if dtype == "float32" else 1e-12     # a sum of two optical depths, rounded
    assert abs(T[2] - 0.35) <= tol, T


@pytest.mark.parametrize("kind", RANGE_KINDS)
def test_issue_example_no_longer_returns_wrong_values(kind):
    """The issue's FOM numbers came from a cut range: every kind now refuses it, naming
    near first (with its value) and then far."""
    seg = _issue_segments("float64")
    with pytest.raises(ValueError, match=r"^near: 0\.3 .* and far: 0\.45 "):
        ad.build(kind, seg, near=0.3, far=0.45)


@pytest.mark.parametrize("kind", [k for k in RANGE_KINDS if "depth_range" in ad.describe(k)["params"]])
@pytest.mark.parametrize("given", [{"near": 0.0}, {"far": 1.0}, {"near": 0.0, "far": 1.0}])
def test_explicit_range_with_per_texel_ranges_names_the_given_argument(kind, given):
    seg = _issue_segments("float32")
    with pytest.raises(ValueError, match=f"^{next(iter(given))}: near=/far= cannot be combined"):
        ad.build(kind, seg, depth_range="texel", **given)


@pytest.mark.parametrize("kind", RANGE_KINDS)
def test_no_content_needs_an_ordered_range(kind):
    """No segments: nothing to contain, the range must still be ordered (names near)."""
    empty = ad.Segments.from_arrays([0, 0], [], [], optical_depth=[])
    with pytest.raises(ValueError, match="^near: need near <=? far"):
        ad.build(kind, empty, near=0.6, far=0.2)
    T = np.asarray(ad.build(kind, empty, near=0.2, far=0.6).eval([0, 0], [0.0, 1.0]))
    assert np.all(T == 1.0)
