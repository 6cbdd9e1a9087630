"""Cheaper reverse-mode paths for the per-texel loops (exact, AVSM).

What reverse mode costs here (measured with drjit 1.5 on the LLVM backend, see
``python -m avsm_dr backward_cost``): a symbolic ``dr.while_loop`` differentiated in
reverse mode with ``max_iterations=M`` replays the loop and keeps its **trajectory in
a per-lane local array of M x (state words)** inside the kernel.  On the CPU that
array lives on the worker's stack (one SIMD packet at a time), so global memory
barely moves, but the stack grows as ``segments per texel x loop state``:

* AVSM-8 (state ~2N + 5 = 21 words) segfaulted at 4000 segments per texel
  (1000 was fine); AVSM-32 at 2000 (500 was fine);
* any loop with ``max_iterations > 65536`` raises ``jit_array_create(): variable
  arrays are limited to a maximum of 65536 elements``;
* on a GPU the same trajectory is per-thread local memory for every thread in flight.

The loop *bound* must also be right: a bound below the true iteration count gives
silently wrong gradients (tests/test_gradients_e2e.py shows it), a larger one only
costs trajectory space.

Two cheaper paths, both exact (same gradients as the plain kernels):

* :class:`ExactRecompute` - the exact curve's loop is a *sum loop*
  (``tau' = tau + tau_i f_i(d)``, the increment does not read ``tau``), so
  ``max_iterations=-1`` selects Dr.Jit's sum-loop fast path: the backward pass re-runs
  the loop (recomputation) and stores no trajectory at all; no 65536 limit.
* :func:`checkpointed_while_loop` / :class:`CheckpointedAVSM` - classic checkpointing
  [Griewank & Walther 2008, ch. 12]: the loop runs in chunks of C iterations with AD
  off, the state is saved at each chunk boundary (M / C states per lane, in global
  memory), and the backward pass re-runs one chunk at a time with AD on, from its
  saved state, in reverse chunk order (one kernel per chunk, so the trajectory of
  only C iterations is ever live).  Costs one extra forward pass.  Forward mode needs
  neither (no trajectory): use it when only a few parameters (directions) matter.
"""
from __future__ import annotations

import drjit as dr
import numpy as np

from . import _arrays as A
from . import backend
from .representations.avsm import AVSM, curve_value, insert_segment, remove_smallest
from .representations.exact import Exact, segment_fraction
from .segments import OPAQUE_OPTICAL_DEPTH

#: Trajectory words per lane a single reverse-differentiated loop may hold
#: (M x state words).  Measured safe: 21 k (AVSM-8, M = 1000) and 34.5 k (AVSM-32,
#: M = 500); measured crashing: 84 k and 138 k.  16 k words = 64 KiB per lane.
TRAJECTORY_BUDGET_WORDS = 16384


def loop_words(kind: str, params: dict | None = None) -> int:
    """Loop state words per lane of a representation's reverse-differentiated loop
    (AVSM: N depths, N values, index, count, two flags, two counters; exact/DSM: index
    and optical depth; linear methods have no loop: 0)."""
    params = params or {}
    if kind == "avsm":
        return 2 * int(params.get("nodes", 8)) + 5
    if kind in ("exact", "dsm"):
        return 2
    return 0


def trajectory_words(kind: str, params: dict | None, max_count: int) -> int:
    """Per-lane trajectory size (words) of reverse mode through ``kind``'s loop with
    ``max_iterations = max_count``: the quantity that grows as segments x state."""
    return int(max_count) * loop_words(kind, params)


def safe_chunk(state_words: int, budget: int = TRAJECTORY_BUDGET_WORDS) -> int:
    """Largest chunk length C whose trajectory ``C x state_words`` fits ``budget``."""
    return max(1, int(budget) // max(1, int(state_words)))


# ----------------------------------------------------------------------------
# Exact curve, sum-loop reverse mode (recomputation, no trajectory)
# ----------------------------------------------------------------------------
class ExactRecompute(Exact):
    """The exact curve; its loop is declared a sum loop (``max_iterations=-1``) in
    :class:`~avsm_dr.representations.exact.Exact` itself, so reverse mode already
    re-runs the loop instead of storing its trajectory.  Kept as the explicit name of
    that strategy for :func:`build_differentiable`."""

    kind = "exact"


# ----------------------------------------------------------------------------
# Checkpointed loops
# ----------------------------------------------------------------------------
def _run_chunk(state, params, cond, body, chunk: int):
    """At most ``chunk`` iterations of the loop (cond, body)(params, *state)."""
    UInt32 = backend.types().UInt32

    def cond_k(k, s):
        return cond(params, *s) & (k < chunk)

    def body_k(k, s):
        return k + 1, tuple(body(params, *s))

    return dr.while_loop((UInt32(0), tuple(state)), cond_k, body_k, max_iterations=chunk,
                         label="checkpoint_chunk")[1]


class _CheckpointedLoop(dr.CustomOp):
    """CustomOp: the primal runs the chunks with AD off and saves each chunk's input
    state; backward re-runs the chunks in reverse order with AD on (one traversal and
    one kernel per chunk); forward mode pushes tangents through the chunks in order."""

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

    def _replay(self, saved):
        s = [dr.detach(x) for x in saved]
        p = [dr.detach(x) for x in self.params]
        dr.enable_grad(s, p)
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
                s = [dr.detach(x) for x in saved]
                p = [dr.detach(x) for x in self.params]
                dr.enable_grad(s, p)
                dr.set_grad(s, tan_s)
                dr.set_grad(p, tan_p)
                out = _run_chunk(s, p, self.cond, self.body, self.chunk)
                dr.forward_to(out)
                tan_s = dr.grad(out)
                dr.eval(tan_s)
        self.set_grad_out(tan_s)

    def name(self):
        return "checkpointed_while_loop"


def checkpointed_while_loop(state, params, cond, body, max_iterations: int, chunk: int):
    """``dr.while_loop`` with checkpointed reverse mode.

    state: tuple of Dr.Jit arrays (flat); params: list of Dr.Jit float arrays the body
    reads (e.g. segment buffers it gathers from) - gradients flow to them and to the
    initial state; cond(params, *state) -> Bool; body(params, *state) -> new state tuple.
    max_iterations: an upper bound of the iteration count (checked: RuntimeError when
    the loop is still active after it).  chunk: iterations per checkpoint (C); memory:
    ``ceil(M / C)`` saved states in global memory + a C-iteration trajectory per lane.
    """
    if not isinstance(chunk, (int, np.integer)) or chunk < 1:
        raise ValueError(f"chunk: expected an integer >= 1, got {chunk!r}")
    out = dr.custom(_CheckpointedLoop, tuple(state), list(params), cond, body,
                    int(max_iterations), int(chunk))
    if dr.any(cond([dr.detach(p) for p in params], *[dr.detach(x) for x in out])):
        raise RuntimeError(f"checkpointed_while_loop: still active after max_iterations={max_iterations} "
                           "(a bound below the true iteration count would give wrong gradients)")
    return out


# ----------------------------------------------------------------------------
# AVSM with checkpointed reverse mode
# ----------------------------------------------------------------------------
class CheckpointedAVSM(AVSM):
    """:class:`~avsm_dr.representations.avsm.AVSM` with ``reverse='checkpoint'``: when the
    segments carry gradients its two build loops run through
    :func:`checkpointed_while_loop` (chunks of ``chunk`` iterations; default
    :func:`safe_chunk` of ``2 N + 5`` state words) whatever the texel length.  Same
    primal and gradients as AVSM.  Not registered: build it directly."""

    def __init__(self, segments, nodes: int = 8, sort: bool = False, interpolation: str = "linear",
                 near: float | None = None, far: float | None = None, *, chunk: int | None = None):
        super().__init__(segments, nodes=nodes, sort=sort, interpolation=interpolation, near=near, far=far,
                         reverse="checkpoint", chunk=chunk)
        self.params["chunk"] = self.chunk


def build_differentiable(kind: str, segments, reverse: str = "auto", **params):
    """Build ``kind`` for differentiation with a chosen reverse-mode strategy.

    reverse: 'trajectory' (the registered kernel: Dr.Jit stores the loop trajectory),
    'recompute' (exact: sum-loop recomputation; avsm: checkpointing) or 'auto'
    (recompute/checkpoint only when ``max segments per texel x loop state`` exceeds
    :data:`TRAJECTORY_BUDGET_WORDS`; exact always recomputes, which costs nothing).
    Other kinds have no per-texel loop (linear methods) or a sum loop (DSM 'curve'
    gradients) and are built as registered.
    """
    from .representations import build
    if reverse not in ("auto", "trajectory", "recompute"):
        raise ValueError(f"reverse: expected 'auto', 'trajectory' or 'recompute', got {reverse!r}")
    if reverse == "trajectory":
        return build(kind, segments, **params)
    if kind == "exact":
        return ExactRecompute(segments, **params)
    if kind == "avsm":
        words = trajectory_words("avsm", params, segments.max_count)
        if reverse == "recompute" or words > TRAJECTORY_BUDGET_WORDS:
            return CheckpointedAVSM(segments, **params)
    return build(kind, segments, **params)


__all__ = ["ExactRecompute", "CheckpointedAVSM", "checkpointed_while_loop", "build_differentiable",
           "loop_words", "trajectory_words", "safe_chunk", "TRAJECTORY_BUDGET_WORDS"]
