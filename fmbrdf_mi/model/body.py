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
tabulated over them with dense matrix products per parameter change
(:func:`body_tables`).  Stokes bases of the tables, in the frame where L has
azimuth 0: incident (travelling along -L) x_in = e_y, outgoing (along V)
x_out = (-sin phi, cos phi, 0): the s directions of the planes of incidence
and exit.  Mirror symmetry gives phi < 0 from phi > 0 with s2 flipped on both
sides.
"""
import math

import drjit as dr
import numpy as np

from .fresnel import transmission_mueller_terms
from .interp import TetraTable
from .quadrature import gauss_legendre, gennormal_unnormalised


class BodyGrid:
    """Resolution of the body quadrature and of its tables.

    The primary table (column 0 of the matrix: what unpolarised light sees)
    is finer than the secondary one (the response to polarised light); both
    resolutions come from tools/check_table.py.
    """

    def __init__(self, n_theta=32, n_phi=64, primary=(65, 129), secondary=(33, 65)):
        self.n_theta, self.n_phi = n_theta, n_phi
        self.primary, self.secondary = primary, secondary


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
#: near grazing, where Fresnel transmittance and masking change fastest, the
#: spacing is cos(A) = 0.17 times the spacing at the pole.
TABLE_WARP = 1.4


def table_theta_of_x(x):
    return (0.5 * math.pi / math.sin(TABLE_WARP)) * np.sin(TABLE_WARP * np.asarray(x))


def table_x_of_theta(theta):
    """Inverse of :func:`table_theta_of_x` (Dr.Jit arrays)."""
    return dr.asin(theta * (math.sin(TABLE_WARP) / (0.5 * math.pi))) * (1.0 / TABLE_WARP)


def table_angles(n_theta, n_phi):
    """Table nodes: theta in [0, pi/2] (both ends, warped), phi in [0, pi] (both ends)."""
    return table_theta_of_x(np.linspace(0.0, 1.0, n_theta)), np.linspace(0.0, math.pi, n_phi)


def body_matrices(dist, eta, kappa, grid, theta_l, theta_v, phi, columns=(0, 1, 2)):
    """Body matrices for every pair of incident angle and outgoing direction.

    ``theta_l`` (n_L,) are the light's polar angles (L at azimuth 0),
    ``theta_v``, ``phi`` (n_V,) the view's polar angle and azimuth.  Returns a
    TensorXf (n_L, n_V, 3, len(columns)): elements (r, s), s in ``columns``, of
    the 3x3 linear block of the body Mueller matrix divided by k_b cos(theta_L).
    Stokes bases: incident x_in = e_y, outgoing x_out = (-sin phi, cos phi, 0),
    the s directions of the planes of incidence and exit, in which the matrix
    varies smoothly (the alpha -> 0 limit is diagonal in them).
    """
    Float = dist.Float
    UInt = dr.uint32_array_t(Float)
    Tensor = dr.tensor_t(Float)
    n, w = microfacet_nodes(dist, grid)
    N = dr.width(w)
    theta_l, theta_v, phi = (Float(np.asarray(x, dtype=np.float64)) if isinstance(x, (np.ndarray, list)) else x
                             for x in (theta_l, theta_v, phi))
    nt, nv = dr.width(theta_l), dr.width(theta_v)

    # --- vMF coupling K (N x N), normalised per column (eq:energy conservation2)
    idx = dr.arange(UInt, N * N)
    p, q = idx // N, idx % N
    np_ = tuple(dr.gather(Float, c, p) for c in n)
    nq_ = tuple(dr.gather(Float, c, q) for c in n)
    e = dr.exp(kappa * (_dot(np_, nq_) - 1.0))
    # Z[p] = sum_q W_q exp(kappa n_q.n_p): normaliser of column p.
    Z = dr.block_sum(dr.gather(Float, w, q) * e, N)
    K = Tensor(e / dr.gather(Float, Z, q), shape=(N, N))

    # --- b_q(L) for every theta_L, L = (sin, 0, cos): incident basis x_in = e_y
    m = N * nt
    idx = dr.arange(UInt, m)
    qi, li = idx // nt, idx % nt
    thL = dr.gather(Float, theta_l, li)
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
    nc = len(columns)
    B = dr.zeros(Float, m * nc)
    for j, s_ in enumerate(columns):
        dr.scatter(B, b[s_], qi * (nc * nt) + li * nc + j)
    B = Tensor(B, shape=(N, nc * nt))

    C = K @ B  # (N, nc nt): c_p(L) = sum_q K_pq b_q(L)

    # --- a_p(V) for every outgoing direction
    m = nv * N
    idx = dr.arange(UInt, m)
    vi, pi_ = idx // N, idx % N
    thV = dr.gather(Float, theta_v, vi)
    phV = dr.gather(Float, phi, vi)
    sph, cph = dr.sincos(phV)
    V = (dr.sin(thV) * cph, dr.sin(thV) * sph, dr.cos(thV))
    npp = tuple(dr.gather(Float, c, pi_) for c in n)
    cos_o = _dot(V, npp)
    tp, tm = transmission_mueller_terms(cos_o, eta)
    s_facet = _normalize(_cross(npp, V), (Float(1.0), Float(0.0), Float(0.0)))
    x_out = (-sph, cph, dr.zeros(Float, m))
    c2, s2 = _rotation(V, s_facet, x_out)
    scale = dr.gather(Float, w, pi_) * dr.maximum(cos_o, 0.0)
    # Stokes [T+, T-, 0] in the facet basis, re-expressed in x_out: s1 = c2 T-, s2 = -s2 T-
    a = (scale * tp, scale * tm * c2, -scale * tm * s2)
    A = dr.zeros(Float, m * 3)
    for r_ in range(3):
        dr.scatter(A, a[r_], (vi * 3 + r_) * N + pi_)
    A = Tensor(A, shape=(3 * nv, N))

    Y = A @ C  # (3 nv, nc nt): rows (v, r), cols (l, s)

    # --- reorder to (l, v, r, s) and divide by pi P(V) P(L)
    per_l = nv * 3 * nc
    idx = dr.arange(UInt, nt * per_l)
    l = idx // per_l
    rest = idx % per_l
    v = rest // (3 * nc)
    rs = rest % (3 * nc)
    r_, s_ = rs // nc, rs % nc
    val = dr.gather(Float, Y.array, (v * 3 + r_) * (nc * nt) + l * nc + s_)
    PL = dr.gather(Float, dist.projected_area(theta_l), l)
    PV = dr.gather(Float, dist.projected_area(theta_v), v)
    return Tensor(val / (math.pi * PL * PV), shape=(nt, nv, 3, nc))


def _table_matrices(dist, eta, kappa, grid, resolution, columns):
    n_theta, n_phi = resolution
    th, ph = table_angles(n_theta, n_phi)
    Y = body_matrices(dist, eta, kappa, grid, th, np.repeat(th, n_phi), np.tile(ph, n_theta), columns)
    return Y.array, (n_theta, n_theta, n_phi)


def body_tables(dist, eta, kappa, grid, polarized=True):
    """The body term as interpolation tables over (x(theta_L), x(theta_V), phi / pi).

    primary: (log M00, M10 / M00, M20 / M00) on ``grid.primary``: everything
    unpolarised incident light sees (only log M00 when not ``polarized``);
    secondary: (M01, M02, M11, M12, M21, M22) / M00 on ``grid.secondary``, the
    response to polarised incident light.  Logarithm and ratios vary more
    smoothly than the elements (a large kappa makes M00 peaked); M is divided by
    k_b cos(theta_L) and expressed in the bases of :func:`body_matrices`.
    Returns (primary, secondary or None) as :class:`TetraTable`.
    """
    Float = dist.Float
    UInt = dr.uint32_array_t(Float)
    vals, shape = _table_matrices(dist, eta, kappa, grid, grid.primary, (0,))
    n = dr.width(vals) // 3
    m00 = dr.maximum(dr.gather(Float, vals, dr.arange(UInt, n) * 3), 1e-30)
    if not polarized:
        return TetraTable(dr.log(m00), shape + (1,)), None
    # elements k = 3 j + c: channel 0 -> log M00, channels 1, 2 -> M10, M20 over M00
    k = dr.arange(UInt, 3 * n)
    m00_k = dr.gather(Float, m00, k // 3)
    primary = dr.select(k % 3 == 0, dr.log(m00_k), dr.gather(Float, vals, k) / m00_k)

    vals, shape2 = _table_matrices(dist, eta, kappa, grid, grid.secondary, (0, 1, 2))
    n2 = dr.width(vals) // 9
    k = dr.arange(UInt, 6 * n2)
    cell, ch = k // 6, k % 6
    elem = ch + 1 + ch // 2  # (M01, M02, M11, M12, M21, M22) -> row-major indices 1, 2, 4, 5, 7, 8
    secondary = dr.gather(Float, vals, cell * 9 + elem) / dr.maximum(dr.gather(Float, vals, cell * 9), 1e-30)
    return TetraTable(primary, shape + (3,)), TetraTable(secondary, shape2 + (6,))
