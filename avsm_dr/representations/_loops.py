"""Reverse mode through per-texel loops: the trajectory budget and checkpointed loops.

Reverse mode through a symbolic ``dr.while_loop`` with ``max_iterations=M`` keeps its
**trajectory in a per-lane local array of M x (state words)** (drjit 1.5; on the CPU on the
worker's stack, which long texels overflow: a segfault).  A bound below the true iteration
count writes past that array, so :func:`run_loop` refuses it (ValueError).

* A *sum loop* (the increment does not read the accumulator) runs with
  ``max_iterations=-1``: reverse mode re-runs the loop and stores no trajectory
  (``loop_state_words = 0``).
* Any other loop is run by :func:`run_loop`: plain while the trajectory fits
  :data:`TRAJECTORY_BUDGET_WORDS`, otherwise :func:`checkpointed_while_loop` (Griewank and
  Walther 2008, "Evaluating Derivatives", ch. 12): chunks of C iterations with AD off, the
  state saved at each chunk boundary, the backward pass re-running one chunk at a time in
  reverse order.

Also the deterministic per-texel sums of the linear kinds (:func:`texel_sums`) and the
chunks of whole texels of the builds that bound their memory (:func:`chunk_stop`).
"""
from __future__ import annotations

import math

import drjit as dr
import numpy as np

from .. import _arrays as A
from .. import backend
from .. import validation as V

#: Trajectory words per lane a reverse-differentiated loop may hold (M x state words; 64 KiB).
TRAJECTORY_BUDGET_WORDS = 16384
#: Reverse-mode strategies accepted by every representation (``reverse=``).
REVERSE_MODES = ("auto", "trajectory", "checkpoint")
#: Fewest non-empty texels (lanes) in a chunk of a build, unless it holds them all: Dr.Jit
#: runs a kernel of one SIMD packet (16 lanes on AVX-512) on the calling thread, which keeps
#: the subnormals that its worker threads flush to zero (area metrics of nodes with T near
#: 1e-300 then tie differently), so a one-packet chunk could place other nodes.
MIN_LANES = 32


def safe_chunk(state_words: int, budget: int = TRAJECTORY_BUDGET_WORDS) -> int:
    """Largest chunk length C whose trajectory ``C x state_words`` fits ``budget``."""
    return max(1, int(budget) // max(1, int(state_words)))


def _run_chunk(state, params, cond, body, chunk: int):
    """At most ``chunk`` iterations of the loop (cond, body)(params, *state)."""
    return dr.while_loop((backend.types().UInt32(0), tuple(state)), lambda k, s: cond(params, *s) & (k < chunk),
                         lambda k, s: (k + 1, tuple(body(params, *s))), max_iterations=chunk,
                         label="checkpoint_chunk")[1]


class _CheckpointedLoop(dr.CustomOp):
    """The primal runs the chunks with AD off, saving each chunk's input state; backward
    re-runs them in reverse order with AD on; forward mode pushes tangents through in order."""

    def eval(self, state, params, cond, body, max_iterations, chunk):
        self.cond, self.body, self.chunk, self.params = cond, body, int(chunk), params
        self.saved = []
        n_chunks = -(-int(max_iterations) // self.chunk) if max_iterations > 0 else 0
        active = dr.any(cond(params, *state))
        for _ in range(n_chunks):
            if not active:
                break
            self.saved.append(state)
            state = _run_chunk(state, params, cond, body, self.chunk)
            dr.eval(state)
            active = dr.any(cond(params, *state))
        return state

    def _replay(self, saved, tangents=None):
        """One chunk re-run from its saved state with AD on (``tangents``: of state, params)."""
        s = [dr.detach(x) for x in saved]
        p = [dr.detach(x) for x in self.params]
        dr.enable_grad(s, p)
        if tangents is not None:
            dr.set_grad(s, tangents[0])
            dr.set_grad(p, tangents[1])
        return s, p, _run_chunk(s, p, self.cond, self.body, self.chunk)

    def backward(self):
        adj = self.grad_out()
        grad_p = None
        for saved in reversed(self.saved):
            with dr.isolate_grad():
                s, p, out = self._replay(saved)
                dr.set_grad(out, adj)
                dr.enqueue(dr.ADMode.Backward, out)
                dr.traverse(dr.ADMode.Backward)
                adj = dr.grad(s)
                g = dr.grad(p)
                grad_p = g if grad_p is None else [a + b for a, b in zip(grad_p, g)]
                dr.eval(adj, grad_p)
        if grad_p is not None:
            self.set_grad_in("params", grad_p)
        self.set_grad_in("state", adj)

    def forward(self):
        tan_s = self.grad_in("state")
        tan_p = self.grad_in("params")
        for saved in self.saved:
            with dr.isolate_grad():
                out = self._replay(saved, (tan_s, tan_p))[2]
                dr.forward_to(out)
                tan_s = dr.grad(out)
                dr.eval(tan_s)
        self.set_grad_out(tan_s)

    def name(self):
        return "checkpointed_while_loop"


def checkpointed_while_loop(state, params, cond, body, max_iterations: int, chunk: int):
    """``dr.while_loop`` with checkpointed reverse mode: ``cond(params, *state)``,
    ``body(params, *state)``; gradients flow to ``params`` (Dr.Jit arrays the body reads)
    and the initial state.  ``max_iterations``: an upper bound (RuntimeError when the loop
    is still active after it); ``chunk``: iterations per checkpoint (C): ``ceil(M / C)``
    saved states plus a C-iteration trajectory per lane."""
    V.integer(chunk, "chunk", 1)
    out = dr.custom(_CheckpointedLoop, tuple(state), list(params), cond, body, int(max_iterations), int(chunk))
    if dr.any(cond([dr.detach(p) for p in params], *[dr.detach(x) for x in out])):
        raise RuntimeError(f"checkpointed_while_loop: still active after max_iterations={max_iterations} "
                           "(a bound below the true iteration count would give wrong gradients)")
    return out


def run_loop(state, params, cond, body, max_iterations: int, checkpoint_chunk: int | None, label: str,
             iterations: int | None = None):
    """Run ``cond``/``body`` over ``state`` (both take ``params`` first): a plain
    ``dr.while_loop`` bounded by ``max_iterations`` when ``checkpoint_chunk`` is None, else
    :func:`checkpointed_while_loop`.  ValueError when ``max_iterations`` is below
    ``iterations`` (the most any lane runs): reverse mode would write past its trajectory."""
    if iterations is not None and max_iterations >= 0 and int(iterations) > int(max_iterations):
        raise ValueError(f"max_iterations: {max_iterations} is below the {int(iterations)} iterations "
                         f"of loop {label!r} (its reverse mode would write past a {max_iterations}-entry "
                         "trajectory)")
    if checkpoint_chunk is not None:
        return checkpointed_while_loop(state, params, cond, body, max_iterations, checkpoint_chunk)
    return dr.while_loop(state, lambda *s: cond(params, *s), lambda *s: body(params, *s),
                         max_iterations=max_iterations, label=label)


def count_sorted(value_at, start, count, x, max_count: int, strict: bool = False):
    """Per lane: how many of the sorted values ``value_at(start + i, active)``, i in
    [0, count) (at most ``max_count``), are ``< x`` (strict) or ``<= x``; unrolled binary search."""
    U32 = backend.types().UInt32
    lo, hi = dr.zeros(U32, dr.width(x)), U32(count)
    for _ in range(max(1, math.ceil(math.log2(max_count + 1)))):
        live = lo < hi
        mid = (lo + hi) >> 1
        val = value_at(start + mid, live)
        below = (val < x) if strict else (val <= x)
        lo = dr.select(live & below, mid + 1, lo)
        hi = dr.select(live & ~below, mid, hi)
    return lo


def texel_lanes(segments):
    """(texel, first, stop) of the non-empty texels (UInt32 each, texel order): the texel
    index and its CSR range ``[first, stop)`` of segments."""
    UInt32 = backend.types().UInt32
    texel = A.to_uint32(np.nonzero(segments.counts > 0)[0])
    offsets = segments.offsets_dr()
    return texel, dr.gather(UInt32, offsets, texel), dr.gather(UInt32, offsets, texel + 1)


def chunk_stop(offsets: np.ndarray, t0: int, per_chunk: int) -> int:
    """End ``t1`` of the chunk of whole texels from ``t0`` (``offsets``: (T+1,) CSR) of about
    ``per_chunk`` segments (at least one texel) with at least :data:`MIN_LANES` non-empty
    texels and as many left after it; T (the rest) where that cannot be."""
    n, lanes = offsets.size - 1, np.r_[0, np.cumsum(np.diff(offsets) > 0)]
    t1 = max(int(np.searchsorted(offsets, offsets[t0] + per_chunk, side="right")) - 1, t0 + 1,
             int(np.searchsorted(lanes, lanes[t0] + MIN_LANES)))
    t1 = min(t1, int(np.searchsorted(lanes, lanes[-1] - MIN_LANES, side="right")) - 1)
    return t1 if t1 > t0 and lanes[t1] - lanes[t0] >= MIN_LANES else n


def texel_sums(segments, term, n: int, label: str = "texel_sum"):
    """Per-texel sums of per-segment terms in a fixed order: one lane per non-empty texel
    loops over its segments i in CSR order, adding ``term(i, texel)`` (``n`` values, inside
    a symbolic loop: no ``dr.eval``).  The same bits whatever the threads (unlike a
    scatter-add); no reverse mode.  Returns (texel UInt32, sums: n evaluated arrays)."""
    texel, first, stop = texel_lanes(segments)
    def body(i, *acc):
        return (i + 1, *[a + x for a, x in zip(acc, term(i, texel))])

    state = (first, *[dr.zeros(segments.Float, dr.width(texel)) for _ in range(n)])
    _, *sums = dr.while_loop(state, lambda i, *acc: i < stop, body, label=label)
    dr.eval(*sums)          # one loop kernel (each later use would otherwise re-run it)
    return texel, sums
