"""Power moments of the absorbance (4, 6, 8) and the Hamburger bound, in float64 NumPy by
a different route from the kernel: moments by Gauss-Legendre quadrature (linear warp: in
u, exact for polynomials; log warp: in t = ln z, where the integrand x(t)^k e^t is entire),
the canonical representation by ``numpy.linalg.solve`` on the Hankel matrix,
``numpy.roots`` and a Vandermonde solve for the weights.
Conventions as in avsm_dr/representations/moments.py (x = 2u - 1, u the warped depth,
bias ``m = (1 - alpha) b / b_0 + alpha m*``)."""
from __future__ import annotations

import numpy as np

from . import linear_ref as R

MBOIT_TARGET = {4: (0.0, 0.375, 0.0, 0.375),
                6: (0.0, 0.48, 0.0, 0.451, 0.0, 0.45),
                8: (0.0, 0.75, 0.0, 0.67666666666666664, 0.0, 0.63, 0.0, 0.60030303030303034)}
UNIFORM_TARGET = {n: tuple(0.0 if k % 2 else 1.0 / (k + 1) for k in range(1, n + 1)) for n in (4, 6, 8)}
GL_X, GL_W = np.polynomial.legendre.leggauss(64)


def power_functions(n=4):
    return [(lambda u, k=k: (2 * u - 1.0) ** k) for k in range(n + 1)]


def moments(case, n=4, warp="linear", **rng):
    """(T, n + 1) b_k = sum_i tau_i E_i[x^k] (optical depth uniform in z per segment)."""
    if warp == "linear":
        return R.basis_coefficients(case, power_functions(n), **rng)
    near, span = R.ranges(case, **rng)
    T = len(case["offsets"]) - 1
    out = np.zeros((T, n + 1))
    k = np.arange(n + 1)
    for t in range(T):
        if case["offsets"][t + 1] == case["offsets"][t]:
            continue
        lo, hi = near[t], near[t] + span[t]
        ln_lo, ls = np.log(lo), max(np.log(hi) - np.log(lo), 1e-6)

        def x_of(ln_z):
            return 2 * (ln_z - ln_lo) / ls - 1

        for z0, z1, tau in R.segments_of(case, t):
            c0, c1, tin, tfront = R.split(z0, z1, tau, lo, span[t])
            a, b = np.log(min(max(z0, lo), hi)), np.log(min(max(z1, lo), hi))
            if b > a:
                tt = 0.5 * (a + b) + 0.5 * (b - a) * GL_X      # t = ln z
                wz = 0.5 * (b - a) * GL_W * np.exp(tt)          # dz = e^t dt
                mean = (x_of(tt)[None, :] ** k[:, None]) @ wz / wz.sum()
            else:
                mean = x_of(a) ** k
            out[t] += tin * mean + tfront * (-1.0) ** k
    return out


def canonical(m, x):
    """Support points (x first, then the roots) and weights of the canonical
    representation through x of the normalised moments m = (1, m_1, .., m_2n)."""
    n = (len(m) - 1) // 2
    B = np.array([[m[i + j] for j in range(n + 1)] for i in range(n + 1)])
    c = np.linalg.solve(B, x ** np.arange(n + 1))
    z = np.sort(np.roots(c[::-1]).real)          # fewer than n when c_n = 0 (a root at infinity)
    points = np.array([x, *z])
    w = np.linalg.solve(np.vander(points, points.size, increasing=True).T, m[:points.size])
    return points, w


def bounds(b, x, alpha, target=None):
    """(lower, upper) absorbance fraction in front of x from one texel's moments b."""
    if b[0] <= 0:
        return 0.0, 0.0
    n = len(b) - 1
    target = MBOIT_TARGET[n] if target is None else target
    m = (1 - alpha) * np.asarray(b, np.float64) / b[0] + alpha * np.concatenate([[1.0], target])
    points, w = canonical(m, x)
    lower = float(w[1:][points[1:] < x].sum())
    return lower, lower + float(w[0])


def optical_depth(b, u, alpha, beta, target=None):
    """D = b_0 clamp(L + beta w_f, 0, 1); 0 at u <= 0 and b_0 at u >= 1."""
    out = np.zeros(len(u))
    for j, uj in enumerate(u):
        if uj <= 0 or b[0] <= 0:
            continue
        if uj >= 1:
            out[j] = b[0]
            continue
        lo, up = bounds(b, 2 * uj - 1, alpha, target)
        out[j] = b[0] * min(max(lo + beta * (up - lo), 0.0), 1.0)
    return out


def warped_u(depth, near, span, warp="linear"):
    """Normalised receiver depth u in [0, 1] under the warp."""
    if warp == "linear":
        return np.clip((depth - near) / span, 0, 1)
    ls = np.maximum(np.log(near + span) - np.log(near), 1e-6)
    return np.clip((np.log(np.maximum(depth, near)) - np.log(near)) / ls, 0, 1)


# ----------------------------------------------------------------- trigonometric
def trig_moments(case, n, warp="linear", **rng):
    """(T, 2n + 1) [b_0, Re b_1, Im b_1, ..], b_k = sum tau E[e^{i k phi}], phi = (pi/2) x, from
    the power-moment route's quadrature (moments() with the functions of phi instead)."""
    if warp == "linear":
        fs = [lambda u: np.ones_like(u)]
        for k in range(1, n + 1):
            fs += [(lambda u, k=k: np.cos(k * np.pi / 2 * (2 * u - 1))),
                   (lambda u, k=k: np.sin(k * np.pi / 2 * (2 * u - 1)))]
        return R.basis_coefficients(case, fs, **rng)
    near, span = R.ranges(case, **rng)
    T = len(case["offsets"]) - 1
    out = np.zeros((T, 2 * n + 1))
    k = np.arange(1, n + 1)

    def f(x):
        x = np.atleast_1d(x)
        ph = np.pi / 2 * x
        rows = [np.ones_like(x)]
        for kk in k:
            rows += [np.cos(kk * ph), np.sin(kk * ph)]
        return np.array(rows)

    for t in range(T):
        if case["offsets"][t + 1] == case["offsets"][t]:
            continue
        lo, hi = near[t], near[t] + span[t]
        ln_lo, ls = np.log(lo), max(np.log(hi) - np.log(lo), 1e-6)
        for z0, z1, tau in R.segments_of(case, t):
            _, _, tin, tfront = R.split(z0, z1, tau, lo, span[t])
            a, b = np.log(min(max(z0, lo), hi)), np.log(min(max(z1, lo), hi))
            if b > a:
                tt = 0.5 * (a + b) + 0.5 * (b - a) * GL_X
                wz = 0.5 * (b - a) * GL_W * np.exp(tt)
                mean = f(2 * (tt - ln_lo) / ls - 1) @ wz / wz.sum()
            else:
                mean = f(2 * (a - ln_lo) / ls - 1)[:, 0]
            out[t] += tin * mean + tfront * f(-1.0)[:, 0]
    return out


def trig_canonical(t, phi_f):
    """Canonical representation on the unit circle through phi_f of the trigonometric
    moments t_0 = 1, t_1..t_n (Toeplitz route): G_jk = t_{k-j}, c = G^-1 conj(z_f)^k, the
    roots of sum c_k z^k (on the unit circle), weights by least squares on t_0..t_n.
    Returns (angles, weights, residual of the moment fit)."""
    n = len(t) - 1

    def tk(k):
        return t[k] if k >= 0 else np.conj(t[-k])

    G = np.array([[tk(k - j) for k in range(n + 1)] for j in range(n + 1)])
    zf = np.exp(1j * phi_f)
    c = np.linalg.solve(G, np.conj(zf) ** np.arange(n + 1))
    roots = np.roots(c[::-1])
    ang = np.r_[phi_f, np.angle(roots)]
    A = np.exp(1j * np.outer(np.arange(n + 1), ang))
    A2 = np.vstack([A.real, A.imag])
    rhs = np.r_[np.real(t), np.imag(t)]
    w = np.linalg.lstsq(A2, rhs, rcond=None)[0]
    return ang, w, float(np.abs(A2 @ w - rhs).max()), float(np.abs(np.abs(roots) - 1).max())


def trig_bounds(b, x, alpha):
    """(lower, upper) absorbance fraction in front of warped x from [b_0, Re b_1, Im b_1, ..]
    (bias toward the uniform distribution on the circle; cut at phi = pi)."""
    if b[0] <= 0:
        return 0.0, 0.0
    t = np.r_[1.0, (1 - alpha) * (np.asarray(b[1::2]) + 1j * np.asarray(b[2::2])) / b[0]]
    ang, w, _, _ = trig_canonical(t, np.pi / 2 * x)
    lower = float(w[1:][ang[1:] < ang[0]].sum())
    return lower, lower + float(w[0])
