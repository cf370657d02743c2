"""The body matrices as the dense double sum over the node set (no Fourier transform).

sum_pq a_p(V) K_pq b_q(L)^T with the N x N coupling K built explicitly, for
any view azimuth: the definition that :mod:`.body`'s azimuthal construction
reproduces at view azimuths on the node grid, and its trigonometric
interpolation approximates between them.  It costs O(N^2) per material and
O(N) per direction; tools/check_accuracy.py --table-only uses it as the direct evaluation of
the quadrature.
"""
import math

import drjit as dr
import numpy as np

from .body import dot3, microfacet_nodes, transmitted


def body_matrices(dist, eta, kappa, grid, theta_l, theta_v, phi, columns=(0, 1, 2)):
    """Body matrices for every pair of incident angle and outgoing direction.

    ``theta_l`` (n_L,) are the light's polar angles (L at azimuth 0),
    ``theta_v``, ``phi`` (n_V,) the view's polar angle and azimuth.  Returns a
    TensorXf (n_L, n_V, 3, len(columns)): elements (r, s), s in ``columns``, of
    the 3x3 linear block of the body Mueller matrix divided by k_b cos(theta_L),
    in the bases of :mod:`.body` (x_in = e_y, x_out = (-sin phi, cos phi, 0)).
    """
    Float = dist.Float
    UInt = dr.uint32_array_t(Float)
    Tensor = dr.tensor_t(Float)
    n, w = microfacet_nodes(dist, grid)
    N = dr.width(w)
    theta_l, theta_v, phi = (Float(np.asarray(x, dtype=np.float64)) if isinstance(x, (np.ndarray, list)) else x
                             for x in (theta_l, theta_v, phi))
    nt, nv, nc = dr.width(theta_l), dr.width(theta_v), len(columns)

    # vMF coupling K (N x N), normalised per column (eq:energy conservation2)
    idx = dr.arange(UInt, N * N)
    p, q = idx // N, idx % N
    e = dr.exp(kappa * (dot3([dr.gather(Float, c, p) for c in n], [dr.gather(Float, c, q) for c in n]) - 1.0))
    Z = dr.block_sum(dr.gather(Float, w, q) * e, N)  # Z[p] = sum_q W_q exp(kappa n_q.n_p)
    K = Tensor(e / dr.gather(Float, Z, q), shape=(N, N))

    # b_q(L) for every theta_L (L at azimuth 0): B (N, nc nt)
    idx = dr.arange(UInt, N * nt)
    qi, li = idx // nt, idx % nt
    b = transmitted(Float, eta, dr.gather(Float, theta_l, li), Float(0.0),
                    [dr.gather(Float, c, qi) for c in n], dr.gather(Float, w, qi), incident=True)
    B = dr.zeros(Float, N * nt * nc)
    for j, s_ in enumerate(columns):
        dr.scatter(B, b[s_], qi * (nc * nt) + li * nc + j)
    C = K @ Tensor(B, shape=(N, nc * nt))

    # a_p(V) for every outgoing direction: A (3 nv, N)
    idx = dr.arange(UInt, nv * N)
    vi, pi_ = idx // N, idx % N
    a = transmitted(Float, eta, dr.gather(Float, theta_v, vi), dr.gather(Float, phi, vi),
                    [dr.gather(Float, c, pi_) for c in n], dr.gather(Float, w, pi_), incident=False)
    A = dr.zeros(Float, nv * N * 3)
    for r_ in range(3):
        dr.scatter(A, a[r_], (vi * 3 + r_) * N + pi_)
    Y = Tensor(A, shape=(3 * nv, N)) @ C  # rows (v, r), cols (l, s)

    # reorder to (l, v, r, s) and divide by pi P(V) P(L)
    idx = dr.arange(UInt, nt * nv * 3 * nc)
    l = idx // (nv * 3 * nc)
    v = (idx // (3 * nc)) % nv
    r_ = (idx // nc) % 3
    s_ = idx % nc
    val = dr.gather(Float, Y.array, (v * 3 + r_) * (nc * nt) + l * nc + s_)
    PL = dr.gather(Float, dist.projected_area(theta_l), l)
    PV = dr.gather(Float, dist.projected_area(theta_v), v)
    return Tensor(val / (math.pi * PL * PV), shape=(nt, nv, 3, nc))
