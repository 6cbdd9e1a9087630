"""Bounds of the absorbance fraction in front of a depth from 2n power moments
(n = 2, 3, 4: 4, 6 or 8 moments), branch-free Dr.Jit, one lane per receiver.

Theory (Peters and Klein 2015, "Moment Shadow Mapping", sec. 3 and algorithm 2;
Muenstermann, Krumpen, Klein, Peters 2018, "Moment-Based Order-Independent Transparency",
sec. 3): for normalised moments ``m = (1, m_1, .., m_2n)`` with a positive definite Hankel
matrix ``B = [m_{i+j}]_{i,j=0..n}`` and a depth ``x_f``, the canonical representation
containing ``x_f`` is supported on ``x_f`` and the n real roots of the kernel polynomial
``c(z) = sum_k c_k z^k``, ``B c = (1, x_f, .., x_f^n)``.  Its weights give the sharp
Chebyshev-Markov-Stieltjes bounds ``L = sum_{z_i < x_f} w_i <= F(x_f-)``,
``U = L + w_f >= F(x_f)`` for every distribution with these moments.

Steps (:func:`hankel_bound`):
1. bias: ``m = (1 - alpha) b / b_0 + alpha m*`` toward a target with a positive definite
   Hankel matrix ``B*``; then ``B >= alpha B*`` and each LDL^T pivot of ``B`` is at least
   ``alpha`` times that of ``B*``: the pivots are floored there;
2. LDL^T of ``B``, forward / back substitution for ``c`` (:func:`kernel_polynomial`);
3. roots of ``c`` (:func:`real_roots`), clipped to ``[-BIG, BIG]``;
4. weights by the Lagrange form on moments 0..n,
   ``w_p = E[prod_{r != p} (z - r)] / prod_{r != p} (p - r)``, clipped to [0, 1];
   ``L = sum_{z_i < x_f} w_i`` (``1 - w_f`` when ``x_f`` is behind every root),
   ``U = min(L + w_f, 1)``; the optical depth in front is ``b_0 clamp(L + beta w_f, 0, 1)``.
"""
from __future__ import annotations

import math

import drjit as dr
import numpy as np

#: Roots are clipped to [-BIG, BIG] (a root escaping to infinity carries weight ~ 0).
BIG = 1e6
#: Safeguarded Newton steps on the kernel polynomial after the closed forms (degree >= 3).
POLISH = 3
#: Guard of divisions (|den| below it is replaced by it).
TINY = 1e-30
#: A texel whose zeroth moment (total optical depth) is at most this is empty (D = 0): its
#: higher moments (``|b_k| <= b_0``) may be flushed to 0 in float32, moments of no
#: distribution; ``T = exp(-b_0)`` is 1 there in float32 and float64 alike.
NEGLIGIBLE = 1e-20
#: Relative floor of the leading coefficient in the cubic / quartic closed forms
#: (float32, float64): see :func:`_leading`.
LEAD = {False: 1e-3, True: 1e-6}


def hankel_pivots(target, m0: float = 1.0) -> list[float]:
    """LDL^T pivots of the Hankel matrix of ``(m0, *target)`` (float64): the floors of step 1
    are ``alpha`` times these.  ValueError when the target's matrix is not positive definite."""
    m = np.concatenate([[m0], np.asarray(target, np.float64)])
    n = (m.size - 1) // 2
    H = np.array([[m[i + j] for j in range(n + 1)] for i in range(n + 1)])
    try:
        L = np.linalg.cholesky(H)
    except np.linalg.LinAlgError:
        raise ValueError("bias_target: the Hankel matrix of the target moments is not positive definite") from None
    return [float(v) for v in np.diag(L) ** 2]


def quadratic_roots(c0, c1, c2):
    """Roots (z2 <= z3) of c0 + c1 z + c2 z^2 (real-rooted; stable form, a vanishing c2
    sends one root to +-BIG)."""
    disc = dr.sqrt(dr.maximum(c1 * c1 - 4 * c0 * c2, 0))
    q = -0.5 * (c1 + dr.select(c1 >= 0, disc, -disc))
    q = dr.select(dr.abs(q) > 1e-30, q, 1e-30)
    ra = dr.clip(q / dr.select(dr.abs(c2) > 1e-30, c2, 1e-30), -BIG, BIG)
    rb = dr.clip(c0 / q, -BIG, BIG)
    return dr.minimum(ra, rb), dr.maximum(ra, rb)


def _cubic_scale(p, q):
    """r = sqrt(|p| / 3), floored at 1e-4 |q|^(1/3) and 1e-10 so that q / (2 r^3) stays
    finite in float32 (the formulas below tend to cbrt(-q) as p -> 0)."""
    return dr.maximum(dr.sqrt(dr.abs(p) * (1 / 3)), dr.maximum(1e-4 * dr.cbrt(dr.abs(q)), 1e-10))


def _largest_cubic_root(p, q):
    """Largest real root of t^3 + p t + q without forming the discriminant (no overflow
    of p^3, q^2 in float32), with a = q / (2 r^3), r = :func:`_cubic_scale`:
    p < 0, |a| <= 1 (three real roots): 2 r cos(acos(-a) / 3);
    p < 0, |a| > 1: -2 sign(q) r cosh(acosh(|a|) / 3);  p >= 0: -2 r sinh(asinh(a) / 3)."""
    r = _cubic_scale(p, q)
    a = q / (2 * r * r * r)
    three = 2 * r * dr.cos(dr.acos(dr.clip(-a, -1, 1)) * (1 / 3))
    one_neg = -2 * dr.sign(q) * r * dr.cosh(dr.acosh(dr.maximum(dr.abs(a), 1)) * (1 / 3))
    one_pos = -2 * r * dr.sinh(dr.asinh(a) * (1 / 3))
    return dr.select(p >= 0, one_pos, dr.select(dr.abs(a) <= 1, three, one_neg))


def _leading(c):
    """The leading coefficient kept at least LEAD x max_k |c_k| in magnitude: a root
    beyond ~1 / LEAD (escaping to infinity as c_n -> 0) stays finite in the closed forms,
    and the polish on the true coefficients restores the other roots."""
    M = dr.abs(c[0])
    for ck in c[1:]:
        M = dr.maximum(M, dr.abs(ck))
    floor = dr.maximum(LEAD[dr.type_v(M) == dr.VarType.Float64] * M, TINY)
    cn = c[-1]
    return dr.select(dr.abs(cn) >= floor, cn, dr.select(cn < 0, -floor, floor))


def _horner(c, z):
    """(c(z), c'(z)) for coefficients c[0..n] (ascending)."""
    p, dp = c[-1] + 0 * z, 0 * z
    for ck in reversed(c[:-1]):
        dp = dp * z + p
        p = p * z + ck
    return p, dp


def _polish(c, roots):
    """POLISH safeguarded Newton steps on c for each root (kept where |c| decreases; the
    derivative kept at least TINY in magnitude), then the 3 or 4 roots sorted ascending."""
    out = []
    for z in roots:
        for _ in range(POLISH):
            p, dp = _horner(c, z)
            zn = dr.clip(z - p / dr.select(dr.abs(dp) > TINY, dp, dr.select(dp < 0, -TINY, TINY)), -BIG, BIG)
            pn, _ = _horner(c, zn)
            z = dr.select(dr.abs(pn) < dr.abs(p), zn, z)
        out.append(z)
    for i, j in {3: [(0, 1), (1, 2), (0, 1)], 4: [(0, 1), (2, 3), (0, 2), (1, 3), (1, 2)]}[len(out)]:
        out[i], out[j] = dr.minimum(out[i], out[j]), dr.maximum(out[i], out[j])     # sorting network
    return out


def cubic_roots(c0, c1, c2, c3):
    """Roots (ascending) of c0 + c1 z + c2 z^2 + c3 z^3, all real: Viete's trigonometric
    formula on the depressed monic cubic t^3 + p t + q (z = t - a2/3, p < 0),
    t_k = 2 r cos(acos(-q / (2 r^3)) / 3 - 2 pi k / 3), r = sqrt(-p/3), then :func:`_polish`."""
    inv = 1 / _leading([c0, c1, c2, c3])
    a2, a1, a0 = c2 * inv, c1 * inv, c0 * inv
    s = a2 * (1 / 3)
    p = a1 - a2 * s
    q = (2 / 27) * a2 * a2 * a2 - s * a1 + a0
    r = _cubic_scale(dr.minimum(p, 0), q)
    th = dr.acos(dr.clip(-q / (2 * r * r * r), -1, 1)) * (1 / 3)
    two_r = 2 * r
    t = [two_r * dr.cos(th - 4 * math.pi / 3), two_r * dr.cos(th - 2 * math.pi / 3), two_r * dr.cos(th)]
    return _polish([c0, c1, c2, c3], [dr.clip(tk - s, -BIG, BIG) for tk in t])


def quartic_roots(c0, c1, c2, c3, c4):
    """Roots (ascending) of c0 + .. + c4 z^4, all real: Ferrari.  Monic depressed form
    y^4 + p y^2 + q y + r (z = y - a3/4); s the largest root of the resolvent
    8 s^3 - 4 p s^2 - 8 r s + 4 p r - q^2; with R = sqrt(2s - p) and
    t = sign(q) sqrt(s^2 - r) (= q / (2R), without the division) the quartic is
    (y^2 - R y + s + t)(y^2 + R y + s - t); then :func:`_polish`."""
    inv = 1 / _leading([c0, c1, c2, c3, c4])
    a3, a2, a1, a0 = c3 * inv, c2 * inv, c1 * inv, c0 * inv
    sh = a3 * 0.25
    sh2 = sh * sh
    p = a2 - 6 * sh2
    q = a1 - 2 * a2 * sh + 8 * sh2 * sh
    r = a0 - a1 * sh + a2 * sh2 - 3 * sh2 * sh2
    # resolvent s^3 - p/2 s^2 - r s + (p r / 2 - q^2 / 8), depressed by s = u + p/6
    A, Bq, C = -0.5 * p, -r, 0.5 * p * r - 0.125 * q * q
    A3 = A * (1 / 3)
    P = Bq - A * A3
    Q = (2 / 27) * A * A * A - A3 * Bq + C
    s = _largest_cubic_root(P, Q) - A3
    R2 = dr.maximum(2 * s - p, 0)
    R = dr.sqrt(R2)
    t = dr.sqrt(dr.maximum(s * s - r, 0))
    t = dr.select(q < 0, -t, t)
    roots = []
    for sign in (1, -1):            # y^2 - sign R y + (s + sign t)
        b, c = -sign * R, s + sign * t
        disc = dr.sqrt(dr.maximum(b * b - 4 * c, 0))
        roots += [0.5 * (-b - disc) - sh, 0.5 * (-b + disc) - sh]
    return _polish([c0, c1, c2, c3, c4], [dr.clip(z, -BIG, BIG) for z in roots])


def _lagrange_weight(m, p, others):
    """Weight at p of the distribution on {p} + others with moments m_0..m_n (Lagrange):
    E[prod_r (z - r)] / prod_r (p - r), from the elementary symmetric polynomials e_k of ``others``."""
    n = len(others)
    e = [1, others[0]]
    for r in others[1:]:
        e = [1] + [e[k] + (r if k == 1 else r * e[k - 1]) if k < len(e) else r * e[k - 1]
                   for k in range(1, len(e) + 1)]
    num = m[n]
    for k in range(1, n + 1):       # + (-1)^k e_k m_{n-k}
        term = e[k] if n - k == 0 else m[n - k] * e[k]
        num = num - term if k % 2 else num + term
    den = p - others[0]
    for r in others[1:]:
        den = den * (p - r)
    return num / dr.select(dr.abs(den) > 1e-30, den, 1e-30)


def kernel_polynomial(m, xf, floors):
    """LDL^T of the Hankel matrix B = [m_{i+j}] (m_0 = 1: L_i0 = m_i, D_0 = 1; pivots
    floored at ``floors[j]``, floats or arrays) and the kernel polynomial's coefficients
    c = B^-1 (1, xf, .., xf^n).  m: list [None, m_1, .., m_2n].  Returns (Lm, D, c)."""
    n = (len(m) - 1) // 2
    Lm = {(i, 0): m[i] for i in range(1, n + 1)}
    D = [None]
    for j in range(1, n + 1):
        acc = m[2 * j] - m[j] * m[j]
        for k in range(1, j):
            acc = acc - Lm[j, k] * Lm[j, k] * D[k]
        D.append(dr.maximum(acc, floors[j]))
        for i in range(j + 1, n + 1):
            acc = m[i + j] - m[i] * m[j]
            for k in range(1, j):
                acc = acc - Lm[i, k] * Lm[j, k] * D[k]
            Lm[i, j] = acc / D[j]
    # ---- solve B c = (1, xf, .., xf^n): L y = v, then D L^T c = y
    v = [None, xf]
    for _ in range(2, n + 1):
        v.append(v[-1] * xf)
    y = [None]
    for i in range(1, n + 1):
        acc = v[i] - m[i]
        for k in range(1, i):
            acc = acc - Lm[i, k] * y[k]
        y.append(acc)
    c = [None] * (n + 1)
    for i in range(n, -1, -1):
        acc = 1 if i == 0 else y[i] / D[i]
        for k in range(i + 1, n + 1):
            acc = acc - Lm[k, i] * c[k]
        c[i] = acc
    return Lm, D, c


def real_roots(c):
    """Roots (ascending) of the real-rooted c_0 + .. + c_n z^n, n = 2, 3, 4 (step 3):
    :func:`quadratic_roots`, :func:`cubic_roots` (Viete) or :func:`quartic_roots` (Ferrari)."""
    return list(quadratic_roots(*c)) if len(c) == 3 else cubic_roots(*c) if len(c) == 4 else quartic_roots(*c)


def hankel_bound(b, xf, alpha, beta, target, floors):
    """Optical depth in front of ``xf`` and the absorbance-fraction bounds from the power
    moments ``b = [b_0, .., b_2n]`` (module docstring).

    b: list of 2n + 1 Dr.Jit arrays (n = 2, 3, 4); xf: Float in [-1, 1]; alpha, beta:
    floats (bias, overestimation); target: the 2n bias-target moments m*_1..m*_2n;
    floors: the LDL^T pivots of the target's Hankel matrix (:func:`hankel_pivots`).
    Returns (D, L, U)."""
    n = (len(b) - 1) // 2
    b0 = b[0]
    empty = b0 <= NEGLIGIBLE
    inv = 1 / dr.select(empty, 1, b0)
    m = [None] + [(1 - alpha) * b[k] * inv + alpha * target[k - 1] for k in range(1, 2 * n + 1)]
    _, _, c = kernel_polynomial(m, xf, [None] + [alpha * f for f in floors[1:]])
    roots = real_roots(c)
    # ---- weights of the canonical representation {xf, roots} (moments 0..n)
    wf = dr.clip(_lagrange_weight(m, xf, roots), 0, 1)
    lower = sum(dr.select(z < xf, dr.clip(_lagrange_weight(m, z, [xf] + roots[:i] + roots[i + 1:]), 0, 1), 0)
                for i, z in enumerate(roots))
    return bounded_depth(b0, empty, dr.select(xf <= roots[-1], lower, 1 - wf), wf, beta)


def bounded_depth(b0, empty, lower, wf, beta):
    """(D, L, U) from the weight ``lower`` in front of the depth and ``wf`` at it (step 4):
    ``L`` clipped to [0, 1], ``U = min(L + w_f, 1)``, ``D = b_0 clamp(L + beta w_f, 0, 1)``
    (0 in an empty texel)."""
    lower = dr.clip(lower, 0, 1)
    upper = dr.minimum(lower + wf, 1)
    frac = dr.clip(lower + beta * wf, 0, 1)
    return dr.select(empty, 0, b0 * frac), lower, upper
