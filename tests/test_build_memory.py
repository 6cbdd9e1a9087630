"""Size parameters are bounded (schema maxima) and every build with a size parameter checks
a byte estimate against :func:`avsm_dr.validation.memory_budget` before allocating
(``osm slices=10**6`` on 1000 texels aborted the process, ``fom
harmonics=10**6`` segfaulted under a 6 GB cap, ``basis n=10**6`` ran 50 s into bad_alloc).

Registry-driven: every kind's schema and every kind with a size parameter are covered.
"""
from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest

import avsm_dr as ad
from avsm_dr import validation as V
from avsm_dr.representations import base as RB

SIZED = [k for k in ad.kinds() if ad.describe(k)["size"] is not None]


def _seg(texels=6, count=4, seed=0):
    rng = np.random.default_rng(seed)
    z0 = rng.uniform(0.0, 1.0, texels * count)
    return ad.Segments.from_arrays(np.arange(texels + 1) * count, z0, z0 + 0.05,
                                   optical_depth=rng.exponential(0.3, texels * count))


@pytest.mark.parametrize("kind", ad.kinds())
def test_every_integer_parameter_has_a_maximum(kind):
    """Every integer parameter of every schema is bounded above (a size parameter without
    one let a single argument ask for any allocation); a float size parameter is bounded
    on the side that grows the build (DSM: tolerance from below)."""
    d = ad.describe(kind)
    for name, p in d["params"].items():
        if p["type"] == "int":
            assert p["max"] is not None, f"{kind}.{name} has no maximum"
    size = d["size"]
    if size is not None and d["params"][size]["type"] == "float":
        p = d["params"][size]
        assert p["max"] is not None or (p["min"] is not None and p["min"] > 0), f"{kind}.{size} unbounded"


def test_base_chunk_has_a_maximum():
    with pytest.raises(ValueError, match=rf"^chunk: expected an integer in \[1, {RB.MAX_CHUNK}\]"):
        ad.build("avsm", _seg(), chunk=RB.MAX_CHUNK + 1)


@pytest.mark.parametrize("params, message", [
    ({"basis": "fourier", "n": 40000}, r"^n: 80001 coefficients per texel, above the 65536 .* n <= 32767 fits"),
    ({"basis": "legendre", "n": 65536},                # list form: ~K/8 kernels (46 s at 65536)
     r"^n: 65536 coefficients per texel, above the 4096 .*MAX_LIST_COEFFICIENTS.* n <= 4096 fits"),
    ({"basis": "power_moments", "n": 5000}, r"^n: 5001 coefficients .* n <= 4095 fits"),
])
def test_coefficients_per_texel_are_capped(params, message):
    """A named basis whose n gives more coefficients than a texel may hold is refused at
    once, with the largest n that fits (the schema's n <= 65536 counts functions)."""
    with pytest.raises(ValueError, match=message):
        ad.build("basis", _seg(), **params)


def test_basis_instance_beyond_the_cap_names_basis():
    from avsm_dr.representations.basis import LegendreBasis
    with pytest.raises(ValueError, match=r"^basis: 5000 coefficients per texel"):
        ad.build("basis", _seg(), basis=LegendreBasis(5000))


@pytest.mark.parametrize("kind", SIZED)
def test_build_beyond_the_budget_is_refused_before_allocating(kind, monkeypatch):
    """A one-byte budget: every kind with a size parameter refuses its headline build with
    a ValueError naming one of its numeric parameters and the budget."""
    monkeypatch.setattr(V, "MEMORY_BUDGET_BYTES", 1)
    d = ad.describe(kind)
    numeric = [n for n, p in d["params"].items() if p["type"] in ("int", "float")] + ["basis"]
    with pytest.raises(ValueError) as info:
        ad.build(kind, _seg(), **d["headline"])
    msg = str(info.value)
    assert msg.split(":")[0] in numeric, msg
    assert "budget" in msg or "MEMORY_BUDGET_BYTES" in msg, msg


def _capture(monkeypatch):
    """Record each memory check's (name, value, need, lo) while running it."""
    seen = []
    original = V.check_memory

    def spy(name, value, need, lo=None, what="", allowed=None):
        seen.append((name, value, need, lo))
        return original(name, value, need, lo=lo, what=what, allowed=allowed)

    monkeypatch.setattr(V, "check_memory", spy)
    return seen


@pytest.mark.parametrize("kind", [k for k in SIZED if k != "dsm"])     # dsm: its own polyline bound
def test_the_value_the_message_says_fits_does_fit(kind, monkeypatch):
    """With the budget one byte below the build's estimate, the message names the largest
    value of the parameter whose estimate fits; a build with that value is accepted."""
    seen = _capture(monkeypatch)
    d = ad.describe(kind)
    params = dict(d["headline"])
    size = d["size"]
    if d["params"][size]["type"] == "int":
        params[size] = max(d["sweep"])
    seg = _seg()
    ad.build(kind, seg, **params)
    name, value, need, lo = seen[0]
    if lo is None or need(lo) >= need(value):
        pytest.skip(f"{kind}: the estimate does not grow with {name}")
    monkeypatch.setattr(V, "MEMORY_BUDGET_BYTES", int(need(value)) - 1)
    with pytest.raises(V.MemoryBudgetError, match=rf"^{name}: .* {name} <= (\S+) fits") as info:
        ad.build(kind, seg, **params)
    fit = type(value)(info.value.args[0].rsplit(f"{name} <= ", 1)[1].split(" fits")[0])
    assert lo <= fit < value and need(fit) <= V.MEMORY_BUDGET_BYTES
    if isinstance(value, int):      # the next value the schema allows (moments: 4, 6, 8) does not fit
        nxt = next(v for v in range(fit + 1, value + 1) if ad.allows(kind, {**params, name: v}))
        assert need(nxt) > V.MEMORY_BUDGET_BYTES
    ad.build(kind, seg, **{**params, name: fit})


def test_budget_follows_the_address_space_limit():
    """The default budget: MEMORY_FRACTION of min(physical memory, RLIMIT_AS), read in a
    subprocess that sets a 6 GB RLIMIT_AS."""
    code = textwrap.dedent("""
        import os, resource
        resource.setrlimit(resource.RLIMIT_AS, (6 << 30, 6 << 30))
        from avsm_dr import validation as V
        phys = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        print(V.memory_budget(), int(V.MEMORY_FRACTION * min(phys, 6 << 30)))
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    got, want = map(int, out.stdout.split())
    assert got == want


CRASHES = textwrap.dedent("""
    import resource, sys
    resource.setrlimit(resource.RLIMIT_AS, (6 << 30, 6 << 30))     # the hostile round's cap
    import numpy as np
    import avsm_dr as ad
    import drjit as dr

    def seg(texels, count=1, grad=False):
        z0 = np.random.default_rng(0).uniform(0, 1, texels * count)
        tau = np.full(texels * count, 0.3)
        if grad:
            tau = ad.backend.types().Float32(tau)
            dr.enable_grad(tau)
        return ad.Segments.from_arrays(np.arange(texels + 1) * count, z0, z0 + 0.01, optical_depth=tau)

    cases = [
        ("slices", lambda: ad.build("osm", seg(1000), slices=10**6)),          # was jit_free() abort
        ("harmonics", lambda: ad.build("fom", seg(1000), harmonics=10**6)),    # was a segfault
        ("n", lambda: ad.build("basis", seg(1000), n=10**6)),                  # was 50 s, bad_alloc
        ("slices", lambda: ad.build("osm", seg(8000), slices=65536)),          # in range: estimate
        # (4000 texels: refused at ~15.6 GiB before the chunked OSM build, now ~2.9 GiB: it builds)
        ("harmonics", lambda: ad.build("fom", seg(20000), harmonics=32767)),   # in range: estimate
        ("n", lambda: ad.build("basis", seg(20000), basis="cosine", n=65536)),
        ("nodes", lambda: ad.build("avsm", seg(4_000_000), nodes=64)),
        ("chunk", lambda: ad.build("avsm", seg(1, 8000, grad=True), nodes=8, reverse="checkpoint",
                                   chunk=8000)),                               # was a segfault
    ]
    for name, case in cases:
        try:
            case()
            print(name, "built")
        except ValueError as exc:
            print(name, "ValueError", str(exc).split(":")[0])
        sys.stdout.flush()
""")


def test_crash_cases_end_with_a_value_error():
    """Each former crash (abort, segfault, bad_alloc under a 6 GB RLIMIT_AS) ends with a
    ValueError naming its parameter, in one subprocess that must exit normally."""
    out = subprocess.run([sys.executable, "-c", CRASHES], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, f"rc {out.returncode}\n{out.stdout}\n{out.stderr[-2000:]}"
    lines = [ln.split() for ln in out.stdout.strip().splitlines()]
    assert len(lines) == 8, out.stdout
    for name, what, *arg in lines:
        assert what == "ValueError" and arg == [name], out.stdout
