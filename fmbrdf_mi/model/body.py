"""The body reflection Mueller matrix (paper eq:observed body reflection Stokes vector).

s_b = 1/(N.V) int int G_m(n) D(n) (V.n) C T(theta_o) D_p(k_b/pi) f(n, n_i)
                     G_s(n_i) D(n_i) (L.n_i) T(theta_i) C  d omega_n d omega_ni  s_i

evaluated by quadrature over a node set {n_p, W_p} of microfacet normals
(PolarMap polar nodes x uniform azimuths).  Because D_p keeps intensity only,
the 4x4 matrix is a sum of outer products

    M = k_b cos(theta_L) / (pi P(V) P(L)) * sum_pq a_p(V) K_pq b_q(L)^T

(Smith: G_m = chi+(V.n) cos(theta_V)/P(V), G_s likewise, P from distribution.py)

* a_p(V) = W_p chi+(V.n_p) (V.n_p) C T(theta_o) e0       - depends on V only
* b_q(L) = W_q chi+(L.n_q) (L.n_q) (e0^T T(theta_i) C)^T - depends on L only
* K_pq = exp(kappa n_p.n_q) / Z(n_q), Z(n_q) = sum_p W_p exp(kappa n_p.n_q)
  (eq:energy conservation2, normalised on the same nodes, so sum_p W_p K_pq = 1
  holds exactly and aliasing of a narrow vMF lobe cannot create energy).

Isotropy leaves three angles (theta_L, theta_V, phi = phi_V - phi_L); the
matrix (its 3x3 linear-polarisation block: D_p removes circular terms) is
tabulated over them with two dense matrix products per parameter change.
Stokes bases of the table, in the frame where L has azimuth 0:
incident (travelling along -L): x_in = e_y;
outgoing (along V): x_out = e_y projected onto the plane normal to V.
Mirror symmetry gives phi < 0 from phi > 0 with s2 flipped on both sides.
"""
import math

import drjit as dr
import numpy as np

from .fresnel import transmission_mueller_terms
from .quadrature import gauss_legendre, gennormal_unnormalised


class BodyGrid:
    """Resolution of the body quadrature and of its table."""

    def __init__(self, n_theta=32, n_phi=64, n_table_theta=65, n_table_phi=129):
        self.n_theta, self.n_phi = n_theta, n_phi
        self.n_table_theta, self.n_table_phi = n_table_theta, n_table_phi


def microfacet_nodes(dist, grid):
    """Normals (x, y, z) and weights W_p = w sin(theta) D(theta) of the node set."""
    Float = dist.Float
    UInt = dr.uint32_array_t(Float)
    u, w = gauss_legendre(grid.n_theta)
    j = dr.arange(UInt, grid.n_theta * grid.n_phi) // grid.n_phi
    k = dr.arange(UInt, grid.n_theta * grid.n_phi) % grid.n_phi
    uu = dr.gather(Float, Float(u), j)
    ww = dr.gather(Float, Float(w), j)
    th = dist.map.theta(uu)
    ph = (Float(k) + 0.5) * (2.0 * math.pi / grid.n_phi)
    st, ct = dr.sin(th), dr.cos(th)
    weight = (ww * dist.map.dtheta_du(uu) * st * (2.0 * math.pi / grid.n_phi)
              * dist.norm * gennormal_unnormalised(th, dist.alpha, dist.beta))
    return (st * dr.cos(ph), st * dr.sin(ph), ct), weight


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _normalize(a, fallback):
    n2 = _dot(a, a)
    ok = n2 > 1e-14
    inv = dr.rsqrt(dr.select(ok, n2, 1.0))
    return tuple(dr.select(ok, a[i] * inv, fallback[i]) for i in range(3))


def _rotation(forward, x_cur, x_new):
    c = _dot(x_cur, x_new)
    s = _dot(forward, _cross(x_cur, x_new))
    return c * c - s * s, 2.0 * c * s


#: Table polar angles are theta = (pi/2) sin(A x) / sin(A), x uniform in [0, 1]:
#: near grazing, where Fresnel transmittance changes fastest, the spacing is
#: cos(A) = 0.36 times the spacing at the pole.
TABLE_WARP = 1.2


def table_theta_of_x(x):
    return (0.5 * math.pi / math.sin(TABLE_WARP)) * np.sin(TABLE_WARP * np.asarray(x))


def table_x_of_theta(theta):
    """Inverse of :func:`table_theta_of_x` (Dr.Jit arrays)."""
    return dr.asin(theta * (math.sin(TABLE_WARP) / (0.5 * math.pi))) * (1.0 / TABLE_WARP)


def table_angles(grid):
    """Table nodes: theta in [0, pi/2] (both ends, warped), phi in [0, pi] (both ends)."""
    return (table_theta_of_x(np.linspace(0.0, 1.0, grid.n_table_theta)),
            np.linspace(0.0, math.pi, grid.n_table_phi))


def body_table(dist, eta, kappa, grid):
    """Body matrix table, shape (n_theta_L, n_theta_V, n_phi, 9), row-major 3x3.

    Entry [i, j, k, 3 r + s] is element (r, s) of the body Mueller matrix
    divided by k_b cos(theta_L), at theta_L = theta[i], theta_V = theta[j],
    phi = phi[k], in the table bases described in the module docstring.
    Returns a Dr.Jit TensorXf of the backend of ``dist.Float``.
    """
    Float = dist.Float
    UInt = dr.uint32_array_t(Float)
    Tensor = dr.tensor_t(Float)
    n, w = microfacet_nodes(dist, grid)
    N = dr.width(w)
    th_tab, ph_tab = table_angles(grid)
    nt, nph = grid.n_table_theta, grid.n_table_phi

    # --- vMF coupling K (N x N), normalised per column (eq:energy conservation2)
    idx = dr.arange(UInt, N * N)
    p, q = idx // N, idx % N
    np_ = tuple(dr.gather(Float, c, p) for c in n)
    nq_ = tuple(dr.gather(Float, c, q) for c in n)
    wp = dr.gather(Float, w, p)
    e = dr.exp(kappa * (_dot(np_, nq_) - 1.0))
    Z = dr.block_sum(dr.gather(Float, w, q) * dr.exp(kappa * (_dot(nq_, np_) - 1.0)), N)  # Z[p] as column normaliser
    # Z[p] = sum_q W_q exp(kappa n_q.n_p): normaliser of column p.
    K = e / dr.gather(Float, Z, q)
    K = Tensor(K, shape=(N, N))

    # --- b_q(L) for every table theta_L, L = (sin, 0, cos): incident basis x_in = e_y
    m = N * nt
    idx = dr.arange(UInt, m)
    qi, li = idx // nt, idx % nt
    thL = dr.gather(Float, Float(th_tab), li)
    L = (dr.sin(thL), dr.zeros(Float, m), dr.cos(thL))
    nq = tuple(dr.gather(Float, c, qi) for c in n)
    cos_i = _dot(L, nq)
    tp, tm = transmission_mueller_terms(cos_i, eta)
    fwd = tuple(-c for c in L)
    s_facet = _normalize(_cross(nq, fwd), (Float(1.0), Float(0.0), Float(0.0)))
    ey = (dr.zeros(Float, m), dr.ones(Float, m), dr.zeros(Float, m))
    c2, s2 = _rotation(fwd, ey, s_facet)
    # Intensity transmitted = T+ s0 + T- s1', s1' = c2 s1 + s2 s2 (s1' in facet basis)
    scale = dr.gather(Float, w, qi) * dr.maximum(cos_i, 0.0)
    b = (scale * tp, scale * tm * c2, scale * tm * s2)
    # B[q, 3 l + s]
    B = dr.zeros(Float, m * 3)
    for s_ in range(3):
        dr.scatter(B, b[s_], qi * (3 * nt) + li * 3 + s_)
    B = Tensor(B, shape=(N, 3 * nt))

    C = K @ B  # (N, 3 nt): c_p(L) = sum_q K_pq b_q(L)

    # --- a_p(V) for every table (theta_V, phi): outgoing basis = e_y projected
    nv = nt * nph
    m = nv * N
    idx = dr.arange(UInt, m)
    vi, pi_ = idx // N, idx % N
    thV = dr.gather(Float, Float(th_tab), vi // nph)
    phV = dr.gather(Float, Float(ph_tab), vi % nph)
    V = (dr.sin(thV) * dr.cos(phV), dr.sin(thV) * dr.sin(phV), dr.cos(thV))
    npp = tuple(dr.gather(Float, c, pi_) for c in n)
    cos_o = _dot(V, npp)
    tp, tm = transmission_mueller_terms(cos_o, eta)
    s_facet = _normalize(_cross(npp, V), (Float(1.0), Float(0.0), Float(0.0)))
    eyv = V[1]
    x_out = _normalize((-eyv * V[0], 1.0 - eyv * V[1], -eyv * V[2]), (Float(1.0), Float(0.0), Float(0.0)))
    c2, s2 = _rotation(V, s_facet, x_out)
    scale = dr.gather(Float, w, pi_) * dr.maximum(cos_o, 0.0)
    # Stokes [T+, T-, 0] in the facet basis, re-expressed in x_out: s1 = c2 T-, s2 = -s2 T-
    a = (scale * tp, scale * tm * c2, -scale * tm * s2)
    A = dr.zeros(Float, m * 3)
    for r_ in range(3):
        dr.scatter(A, a[r_], (vi * 3 + r_) * N + pi_)
    A = Tensor(A, shape=(3 * nv, N))

    Y = A @ C  # (3 nv, 3 nt): rows (v, r), cols (l, s)

    # --- reorder to (l, theta_V, phi, 3 r + s) and divide by pi P(V) P(L)
    total = nt * nv * 9
    idx = dr.arange(UInt, total)
    l = idx // (nv * 9)
    rest = idx % (nv * 9)
    v = rest // 9
    rs = rest % 9
    r_, s_ = rs // 3, rs % 3
    val = dr.gather(Float, Y.array, (v * 3 + r_) * (3 * nt) + l * 3 + s_)
    P = dist.projected_area(Float(th_tab))
    PL = dr.gather(Float, P, l)
    PV = dr.gather(Float, P, v // nph)
    val = val / (math.pi * PL * PV)
    return Tensor(val, shape=(nt, nt, nph, 9))
