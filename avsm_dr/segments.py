"""Occluder segments along light rays, one CSR list per shadow-map texel.

Texel ``k`` owns segments ``offsets[k] : offsets[k+1]``.  Segment ``i`` spans the
light-space depths ``z0[i] <= z1[i]`` and holds a uniform density, so its
transmittance at a depth ``d`` is ``exp(-tau_i * clamp((d - z0_i) / (z1_i - z0_i), 0, 1))``
with ``tau_i`` the segment's optical depth (``-ln`` of its exit transmittance).
A zero-length segment is a step at ``z0`` (a receiver at exactly ``z0`` is behind it).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import drjit as dr
import numpy as np

from . import _arrays as A
from . import backend

#: Optical depth stored for a fully opaque segment (exit transmittance exactly 0).
#: ``exp(-1e4)`` is 0 in float32 and float64 alike, and the value stays finite so
#: that products with zero-length fractions never make NaN.
OPAQUE_OPTICAL_DEPTH = 1.0e4


@dataclass(eq=False)
class Segments:
    """Segments of all texels (CSR).  Build with :meth:`from_arrays`.

    Attributes: ``offsets`` (T+1,) int64 NumPy; ``z0``, ``z1``, ``optical_depth``
    Dr.Jit float arrays of length S (AD graphs kept); ``dtype`` 'float32'|'float64'.
    """

    offsets: np.ndarray
    z0: Any
    z1: Any
    optical_depth: Any
    dtype: str = "float32"
    sorted_by_depth: bool = False
    _cache: dict = field(default_factory=dict, repr=False)

    # ------------------------------------------------------------------ build
    @classmethod
    def from_arrays(cls, offsets, z0, z1, transmittance=None, optical_depth=None,
                    dtype: str | None = None) -> "Segments":
        """Validate and pack segments.

        offsets: (T+1,) non-decreasing integers, offsets[0] = 0, offsets[-1] = S.
        z0, z1: (S,) light-space entry/exit depths, z0 <= z1, finite.
        transmittance: (S,) exit transmittance in [0, 1] (0 = opaque), or
        optical_depth: (S,) tau >= 0 finite (values above OPAQUE_OPTICAL_DEPTH are clamped).
        dtype: 'float32' (default) or 'float64'; default follows Dr.Jit float64 input.
        """
        off = A.host(offsets, "offsets", np.float64)
        if off.ndim != 1 or off.size < 2:
            raise ValueError(f"offsets: expected a 1-D array of T+1 >= 2 entries, got shape {off.shape}")
        A.check_finite(off, "offsets")
        if np.any(off != np.round(off)) or off[0] != 0:
            raise ValueError("offsets: must be integers starting at 0")
        if np.any(np.diff(off) < 0):
            raise ValueError("offsets: must be non-decreasing")
        off = off.astype(np.int64)
        n = int(off[-1])
        z0h = A.host_1d(z0, "z0")
        z1h = A.host_1d(z1, "z1")
        for name, arr in (("z0", z0h), ("z1", z1h)):
            if arr.size != n:
                raise ValueError(f"{name}: length {arr.size} does not match offsets[-1] = {n}")
            A.check_finite(arr, name)
        if np.any(z1h < z0h):
            raise ValueError(f"z1: {int(np.count_nonzero(z1h < z0h))} segment(s) have z1 < z0")
        if (transmittance is None) == (optical_depth is None):
            raise ValueError("transmittance: pass exactly one of transmittance= or optical_depth=")

        if dtype is None:
            dtype = "float32"
            for x in (z0, z1, transmittance, optical_depth):
                if A.is_drjit(x) and A.dtype_of(x) == "float64":
                    dtype = "float64"
        Float = A.float_type(dtype)
        if transmittance is not None:
            th = A.host_1d(transmittance, "transmittance")
            if th.size != n:
                raise ValueError(f"transmittance: length {th.size} does not match offsets[-1] = {n}")
            A.check_finite(th, "transmittance")
            if np.any((th < 0) | (th > 1)):
                raise ValueError("transmittance: values must lie in [0, 1] (opacity above 1 or negative)")
            if n == 0:  # no blockers at all: every texel is empty (T = 1 everywhere)
                return cls(off, Float(), Float(), Float(), dtype)
            t = A.to_float(transmittance, Float)
            tiny = float(np.exp(-OPAQUE_OPTICAL_DEPTH)) if dtype == "float64" else 0.0
            # -ln t, with t = 0 (opaque) mapped to OPAQUE_OPTICAL_DEPTH without an
            # infinite derivative leaking into the AD graph.
            safe = dr.maximum(t, 1e-300 if dtype == "float64" else 1e-38)
            tau = dr.select(t > tiny, dr.minimum(-dr.log(safe), OPAQUE_OPTICAL_DEPTH),
                            OPAQUE_OPTICAL_DEPTH)
        else:
            oh = A.host_1d(optical_depth, "optical_depth")
            if oh.size != n:
                raise ValueError(f"optical_depth: length {oh.size} does not match offsets[-1] = {n}")
            A.check_finite(oh, "optical_depth")
            if np.any(oh < 0):
                raise ValueError("optical_depth: values must be >= 0 (negative density)")
            if n == 0:
                return cls(off, Float(), Float(), Float(), dtype)
            tau = dr.minimum(A.to_float(optical_depth, Float), OPAQUE_OPTICAL_DEPTH)
        return cls(off, A.to_float(z0, Float), A.to_float(z1, Float), tau, dtype)

    # ------------------------------------------------------------ properties
    @property
    def Float(self):
        return type(self.z0)

    @property
    def itemsize(self) -> int:
        """Bytes per stored float (4 for float32, 8 for float64)."""
        return 4 if self.dtype == "float32" else 8

    @property
    def requires_grad(self) -> bool:
        """True when z0, z1 or optical_depth carry gradients."""
        return any(dr.grad_enabled(x) for x in (self.z0, self.z1, self.optical_depth))

    @property
    def n_texels(self) -> int:
        return int(self.offsets.size - 1)

    @property
    def n_segments(self) -> int:
        return int(self.offsets[-1])

    @property
    def counts(self) -> np.ndarray:
        """(T,) number of segments per texel."""
        return np.diff(self.offsets)

    @property
    def max_count(self) -> int:
        return int(self.counts.max()) if self.n_texels else 0

    @property
    def transmittance(self):
        """Exit transmittance exp(-tau) of each segment (Dr.Jit)."""
        return dr.exp(-self.optical_depth)

    def offsets_dr(self):
        """offsets as a Dr.Jit UInt32 array (cached)."""
        if "offsets" not in self._cache:
            self._cache["offsets"] = A.to_uint32(self.offsets)
        return self._cache["offsets"]

    def texel_of_segment(self):
        """(S,) texel index of every segment, Dr.Jit UInt32 (cached)."""
        if "texel_of" not in self._cache:
            idx = np.repeat(np.arange(self.n_texels, dtype=np.uint32), self.counts)
            self._cache["texel_of"] = A.to_uint32(idx)
        return self._cache["texel_of"]

    def bounds(self) -> tuple[float, float]:
        """Global (near, far): min z0 and max z1 over all segments ((0, 1) if none)."""
        if self.n_segments == 0:
            return 0.0, 1.0
        if "bounds" not in self._cache:  # reduced on the device: no host copy of S values
            lo = dr.min(dr.detach(self.z0))
            hi = dr.max(dr.detach(self.z1))
            self._cache["bounds"] = (float(lo[0]), float(hi[0]))
        return self._cache["bounds"]

    def texel_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Tight per-texel (near, far) as float64 NumPy arrays; empty texels get (0, 1)."""
        near = np.zeros(self.n_texels)
        far = np.ones(self.n_texels)
        c = self.counts
        nz = c > 0
        if nz.any():
            z0 = A.host(self.z0, "z0")
            z1 = A.host(self.z1, "z1")
            starts = self.offsets[:-1][nz]
            near[nz] = np.minimum.reduceat(z0, starts)
            far[nz] = np.maximum.reduceat(z1, starts)
        return near, far

    def numpy(self) -> dict[str, np.ndarray]:
        """Host copies (float64) of offsets, z0, z1, optical_depth."""
        return {
            "offsets": self.offsets.copy(),
            "z0": A.host(self.z0, "z0"),
            "z1": A.host(self.z1, "z1"),
            "optical_depth": A.host(self.optical_depth, "optical_depth"),
        }

    # ------------------------------------------------------------- reorder
    def sorted(self) -> "Segments":
        """Segments of each texel sorted by (z0, z1); gradients follow the permutation."""
        if self.sorted_by_depth:
            return self
        h = self.numpy()
        tex = np.repeat(np.arange(self.n_texels), self.counts)
        perm = np.lexsort((h["z1"], h["z0"], tex)).astype(np.uint32)
        idx = A.to_uint32(perm)
        Float = self.Float
        out = Segments(self.offsets, dr.gather(Float, self.z0, idx), dr.gather(Float, self.z1, idx),
                       dr.gather(Float, self.optical_depth, idx), self.dtype, True)
        return out

    def select_texels(self, texels) -> "Segments":
        """A new Segments with only the given texels (in that order)."""
        texels = np.asarray(texels, dtype=np.int64)
        c = self.counts[texels]
        off = np.concatenate([[0], np.cumsum(c)]).astype(np.int64)
        idx = np.concatenate([np.arange(self.offsets[t], self.offsets[t + 1]) for t in texels]) \
            if texels.size else np.zeros(0, np.int64)
        if idx.size == 0:
            Float = self.Float
            return Segments(off, Float(), Float(), Float(), self.dtype, self.sorted_by_depth)
        i = A.to_uint32(idx)
        Float = self.Float
        return Segments(off, dr.gather(Float, self.z0, i), dr.gather(Float, self.z1, i),
                        dr.gather(Float, self.optical_depth, i), self.dtype, self.sorted_by_depth)

    def __repr__(self) -> str:
        return (f"Segments(texels={self.n_texels}, segments={self.n_segments}, "
                f"max_per_texel={self.max_count}, dtype={self.dtype})")
