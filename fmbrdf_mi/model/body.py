"""The body reflection Mueller matrix (paper eq:observed body reflection Stokes vector).

s_b = 1/(N.V) int int G_m(n) D(n) (V.n) C T(theta_o) D_p(k_b/pi) f(n, n_i)
                     G_s(n_i) D(n_i) (L.n_i) T(theta_i) C  d omega_n d omega_ni  s_i

evaluated by quadrature over a node set {n_p, W_p} of microfacet normals: the
product of PolarMap polar nodes theta_j (j < J) and uniform azimuths
phi_k = (k + 1/2) 2 pi / N_az.  Because D_p keeps intensity only, the 4x4
matrix is a sum of outer products

    M = k_b cos(theta_L) / (pi P(V) P(L)) * sum_pq a_p(V) K_pq b_q(L)^T

(Smith: G_m = chi+(V.n) cos(theta_V)/P(V), G_s likewise, P from distribution.py)

* a_p(V) = W_p chi+(V.n_p) (V.n_p) C T(theta_o) e0       - depends on V only
* b_q(L) = W_q chi+(L.n_q) (L.n_q) (e0^T T(theta_i) C)^T - depends on L only
* K_pq = exp(kappa n_p.n_q) / Z(n_q), Z(n_q) = sum_p W_p exp(kappa n_p.n_q)
  (eq:energy conservation2, normalised on the same nodes, so sum_p W_p K_pq = 1
  holds exactly and aliasing of a narrow vMF lobe cannot create energy).

Azimuthal structure (DESIGN.md section 2).  K_pq depends on the azimuths only
through phi_p - phi_q (Z_q on theta_q only): K is block-circulant.  With L at
azimuth 0, b_q depends on phi_q, and with V at azimuth phi_V = n 2 pi / N_az
(on the node grid), a_p(V) is a_p(V at azimuth 0) shifted by n nodes, its
Stokes basis turning with V.  With the discrete Fourier transform over the
node azimuths, X_m = sum_k x(phi_k) exp(-i m phi_k),

    Y(phi_V = n 2 pi / N_az) = (1 / N_az) sum_m  Yhat_m exp(i m phi_V),
    Yhat_m = sum_j conj(Ahat_m[j]) sum_l Khat_m[j, l] Bhat_m[l]        (*)

exactly (the dense double sum over the same nodes, up to rounding): the
N x N coupling becomes N_az/2 + 1 blocks of J x J, and the dependence on
phi = phi_V - phi_L a Fourier series.  Between grid azimuths the series is
the trigonometric interpolant of the grid values (Nyquist term split
symmetrically), which is how the tables' finer phi nodes are filled.
:func:`body_series` computes the coefficients (*) with batched matrix
products, :func:`synthesise` the series; tools/check_accuracy.py --table-only and
tests/test_body_fourier.py measure both against direct sums.

Isotropy leaves three angles (theta_L, theta_V, phi = phi_V - phi_L); the
matrix (its 3x3 linear-polarisation block: D_p removes circular terms) is
tabulated over them per parameter change (:func:`body_tables`).  Stokes bases
of the tables, in the frame where L has azimuth 0: incident (travelling along
-L) x_in = e_y, outgoing (along V) x_out = (-sin phi, cos phi, 0): the s
directions of the planes of incidence and exit.  Mirror symmetry gives
phi < 0 from phi > 0 with s2 flipped on both sides.
"""
import math

import drjit as dr
import numpy as np

from .fresnel import transmission_mueller_terms
from .interp import LineTable, TetraTable
from .quadrature import constant, gauss_legendre_array, gennormal_unnormalised


class BodyGrid:
    """Resolution of the body quadrature and of its tables.

    ``n_theta`` polar x ``n_phi`` azimuthal microfacet nodes (n_phi even);
    ``table``: (n_theta, n_phi) nodes of the body table (docs/benchmarks/accuracy.md
    for how they were chosen).
    """

    def __init__(self, n_theta=32, n_phi=64, table=(49, 81), n_factor=257):
        if n_phi % 2:
            raise ValueError("BodyGrid: n_phi must be even")
        self.n_theta, self.n_phi = n_theta, n_phi
        self.table = tuple(table)
        #: nodes of the 1-D table of the grazing factors (:func:`grazing_factors`)
        self.n_factor = n_factor


def polar_nodes(dist, grid):
    """Polar angles theta_j (J,) and weights W_j = w sin(theta) D(theta) 2 pi / N_az
    of the node set: every azimuth of a polar ring has the same weight."""
    Float = dist.Float
    u, w = gauss_legendre_array(Float, grid.n_theta)
    th = dist.map.theta(u)
    weight = (w * dist.map.dtheta_du(u) * dr.sin(th) * (2.0 * math.pi / grid.n_phi)
              * dist.norm * gennormal_unnormalised(th, dist.alpha, dist.beta))
    return th, weight


def node_azimuths(grid):
    """phi_k = (k + 1/2) 2 pi / N_az (NumPy, float64)."""
    return (np.arange(grid.n_phi) + 0.5) * (2.0 * math.pi / grid.n_phi)


def microfacet_nodes(dist, grid):
    """The whole node set: normals (x, y, z) and weights, p = j N_az + k."""
    Float = dist.Float
    UInt = dr.uint32_array_t(Float)
    th, w = polar_nodes(dist, grid)
    idx = dr.arange(UInt, grid.n_theta * grid.n_phi)
    j, k = idx // grid.n_phi, idx % grid.n_phi
    th, weight = dr.gather(Float, th, j), dr.gather(Float, w, j)
    ph = (Float(k) + 0.5) * (2.0 * math.pi / grid.n_phi)
    st = dr.sin(th)
    return (st * dr.cos(ph), st * dr.sin(ph), dr.cos(th)), weight


def dot3(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _normalize(a, fallback):
    n2 = dot3(a, a)
    ok = n2 > 1e-14
    inv = dr.rsqrt(dr.select(ok, n2, 1.0))
    return tuple(dr.select(ok, a[i] * inv, fallback[i]) for i in range(3))


def _rotation(forward, x_cur, x_new):
    c = dot3(x_cur, x_new)
    s = dot3(forward, _cross(x_cur, x_new))
    return c * c - s * s, 2.0 * c * s


def transmitted(Float, eta, theta_dir, phi_dir, n, w, incident):
    """Stokes channels of a_p (``incident=False``: V, outgoing) or b_q
    (``incident=True``: L) for directions (theta_dir, phi_dir) and nodes
    (normals ``n``, weights ``w``), lane by lane.

    Bases: the s axis of the plane through the direction and the macro normal,
    (-sin phi_dir, cos phi_dir, 0).  a = W chi+ cos_o [T+, T- c, -T- s] (the
    facet's [T+, T-, 0] re-expressed in x_out); b = W chi+ cos_i [T+, T- c, T- s]
    (the row e0^T T C mapping the incident basis to the facet's).
    """
    sth, cth = dr.sin(theta_dir), dr.cos(theta_dir)
    sph, cph = dr.sin(phi_dir), dr.cos(phi_dir)
    d = (sth * cph, sth * sph, cth)
    x_dir = (-sph, cph, dr.zeros(Float, dr.width(sph)))
    cos_t = dot3(d, n)
    tp, tm = transmission_mueller_terms(cos_t, eta)
    one, zero = Float(1.0), Float(0.0)
    scale = w * dr.maximum(cos_t, 0.0)
    if incident:
        fwd = tuple(-c for c in d)
        s_facet = _normalize(_cross(n, fwd), (one, zero, zero))
        c2, s2 = _rotation(fwd, x_dir, s_facet)
        return scale * tp, scale * tm * c2, scale * tm * s2
    s_facet = _normalize(_cross(n, d), (one, zero, zero))
    c2, s2 = _rotation(d, s_facet, x_dir)
    return scale * tp, scale * tm * c2, -scale * tm * s2


def _side_vectors(dist, eta, grid, theta, w_j, th_j, channels, incident, factor):
    """a (or b) for directions at azimuth 0 and polar angles ``theta`` (n,), at
    every node, times ``factor`` (n,), as a tensor (N_az, J * n * len(channels)):
    lanes (k, j, i, c)."""
    Float = dist.Float
    UInt = dr.uint32_array_t(Float)
    J, K = grid.n_theta, grid.n_phi
    nc, n = len(channels), dr.width(theta)
    idx = dr.arange(UInt, K * J * n * nc)
    k = idx // (J * n * nc)
    j = (idx // (n * nc)) % J
    i = (idx // nc) % n
    c = idx % nc
    thn = dr.gather(Float, th_j, j)
    phn = (Float(k) + 0.5) * (2.0 * math.pi / K)
    stn = dr.sin(thn)
    node = (stn * dr.cos(phn), stn * dr.sin(phn), dr.cos(thn))
    w = dr.gather(Float, w_j, j) * dr.gather(Float, factor, i)
    vals = transmitted(Float, eta, dr.gather(Float, theta, i), Float(0.0), node, w, incident)
    chan = dr.gather(UInt, UInt(channels), c) if nc > 1 else UInt(channels[0])
    out = dr.select(chan == 0, vals[0], dr.select(chan == 1, vals[1], vals[2]))
    return dr.tensor_t(Float)(out, shape=(K, J * n * nc))


def _dft_rows(grid, rows):
    """DFT matrix over the node azimuths, ``rows`` per mode m = 0 .. N_az/2:
    'c' cos(m phi_k), 's' -sin(m phi_k), 'C' -cos(m phi_k) (NumPy, float64)."""
    m = np.arange(grid.n_phi // 2 + 1)[:, None]
    ph = node_azimuths(grid)[None, :]
    table = {"c": np.cos(m * ph), "s": -np.sin(m * ph), "C": -np.cos(m * ph)}
    return np.stack([table[r] for r in rows], axis=1).reshape(-1, grid.n_phi)


def coupling_modes(dist, kappa, grid, th_j, w_j):
    """Khat_m[j, l] (M, J, J): the DFT of the block-circulant vMF coupling
    K(j, l, d) = exp(kappa (n_j,0 . n_l,d - 1)) / Z_l over the azimuth
    difference d (real: K is even in d), Z_l = sum_j W_j sum_d exp(...)."""
    Float = dist.Float
    UInt = dr.uint32_array_t(Float)
    Tensor = dr.tensor_t(Float)
    J, K = grid.n_theta, grid.n_phi
    M = K // 2 + 1
    idx = dr.arange(UInt, K * J * J)
    d = idx // (J * J)
    j = (idx // J) % J
    l = idx % J
    tj, tl = dr.gather(Float, th_j, j), dr.gather(Float, th_j, l)
    cos_d = dr.cos(Float(d) * (2.0 * math.pi / K))
    e = dr.exp(kappa * (dr.cos(tj) * dr.cos(tl) + dr.sin(tj) * dr.sin(tl) * cos_d - 1.0))
    cos_md = constant(Tensor, ("cos_md", K),
                       lambda: np.cos(np.arange(M)[:, None] * np.arange(K)[None, :] * (2.0 * math.pi / K)))
    E = cos_md @ Tensor(e, shape=(K, J * J))  # (M, J*J)
    # Z_l = sum_j W_j Ehat_0[j, l]
    lj = dr.arange(UInt, J * J)
    Z = dr.block_sum(dr.gather(Float, w_j, lj % J) * dr.gather(Float, E.array, (lj % J) * J + lj // J), J)
    midx = dr.arange(UInt, M * J * J)
    return Tensor(E.array / dr.gather(Float, Z, midx % J), shape=(M, J, J))


def body_series(dist, eta, kappa, grid, theta_l, theta_v, rows=(0, 1, 2), columns=(0, 1, 2), nodes=None,
                khat=None, proj=None):
    """Fourier coefficients (*) of the body matrices over phi = phi_V - phi_L,
    divided by pi P(V) P(L) (Smith, see the module docstring).

    Returns a tensor (2M, n_L nc n_V nr), M = N_az/2 + 1, rows (m, re/im),
    columns (l, s, v, r): Yhat_m of element (rows[r], columns[s]) of the 3x3
    linear block for theta_L[l], theta_V[v], in the bases of the module
    docstring.  ``nodes`` (:func:`polar_nodes`), ``khat``
    (:func:`coupling_modes`) and ``proj`` (P at theta_L and at theta_V): if
    already computed for this material.
    """
    Float = dist.Float
    Tensor = dr.tensor_t(Float)
    th_j, w_j = nodes if nodes is not None else polar_nodes(dist, grid)
    if khat is None:
        khat = coupling_modes(dist, kappa, grid, th_j, w_j)
    theta_l, theta_v = (Float(np.asarray(x, dtype=np.float64)) if isinstance(x, (np.ndarray, list)) else x
                        for x in (theta_l, theta_v))
    J, M = grid.n_theta, grid.n_phi // 2 + 1
    nl, nv, nr, nc = dr.width(theta_l), dr.width(theta_v), len(rows), len(columns)
    p_l, p_v = proj if proj is not None else (dist.projected_area(theta_l), dist.projected_area(theta_v))
    a = _side_vectors(dist, eta, grid, theta_v, w_j, th_j, tuple(rows), False, 1.0 / (math.pi * p_v))
    b = _side_vectors(dist, eta, grid, theta_l, w_j, th_j, tuple(columns), True, 1.0 / p_l)
    # Ahat: rows (m, re/im) -> (M, 1, 2J, nv nr): [Re; Im] stacked over j
    A = constant(Tensor, ("dft", grid.n_phi, "cs"), lambda: _dft_rows(grid, "cs")) @ a
    A = dr.reshape(Tensor, A, (M, 1, 2 * J, nv * nr))
    # Bhat rows per mode: Re, Im, Im, -Re -> Chat = Khat Bhat -> [Re; Im] and [Im; -Re]
    B = constant(Tensor, ("dft", grid.n_phi, "cssC"), lambda: _dft_rows(grid, "cssC")) @ b
    B = dr.reshape(Tensor, B, (M, 4, J, nl * nc))
    C = dr.reshape(Tensor, dr.reshape(Tensor, khat, (M, 1, J, J)) @ B, (M, 2, 2 * J, nl * nc))
    # Yhat = Chat^T conj(Ahat): Re = Cr^T Ar + Ci^T Ai, Im = Ci^T Ar - Cr^T Ai
    Y = dr.matmul(C, A, At=True)  # (M, 2, nl nc, nv nr)
    return dr.reshape(Tensor, Y, (2 * M, nl * nc * nv * nr))


def synthesis_matrix(grid, phi):
    """(len(phi), 2M) weights of :func:`body_series`'s rows giving the series at
    ``phi``: (w_m / N_az) (cos m phi, -sin m phi), w_0 = w_{N/2} = 1, else 2; the
    Nyquist sine is dropped (symmetric trigonometric interpolation)."""
    K = grid.n_phi
    m = np.arange(K // 2 + 1)
    wm = np.where((m == 0) | (m == K // 2), 1.0, 2.0) / K
    ang = np.asarray(phi, dtype=np.float64)[:, None] * m[None, :]
    S = np.stack([wm * np.cos(ang), -wm * np.sin(ang)], axis=2)
    S[:, -1, 1] = 0.0
    return S.reshape(len(phi), -1)


def synthesise(Float, grid, series, phi):
    """The series of :func:`body_series` at azimuths ``phi`` (NumPy): (n_phi, cols)."""
    phi = np.asarray(phi, dtype=np.float64)
    S = constant(dr.tensor_t(Float), ("synth", grid.n_phi, phi.tobytes()), lambda: synthesis_matrix(grid, phi))
    return S @ series


def body_grid_matrices(dist, eta, kappa, grid, theta_l, theta_v, phi, rows=(0, 1, 2), columns=(0, 1, 2),
                       nodes=None, khat=None, proj=None):
    """Body matrices on the product grid phi x theta_L x theta_V: a tensor
    (n_phi, n_L, n_V, nr, nc) (the tables' order), elements (rows[r],
    columns[s]) of the 3x3 linear block divided by k_b cos(theta_L), in the
    bases of the module docstring."""
    Float = dist.Float
    Tensor = dr.tensor_t(Float)
    theta_l, theta_v = (np.asarray(x, dtype=np.float64) for x in (theta_l, theta_v))
    nl, nv, nt, nr, nc = len(theta_l), len(theta_v), len(phi), len(rows), len(columns)
    series = body_series(dist, eta, kappa, grid, theta_l, theta_v, rows, columns, nodes, khat, proj)
    Y = synthesise(Float, grid, series, phi).array  # (t, l, s, v, r)
    return Tensor(_grid_order(Float, Y, nv, nr, nc), shape=(nt, nl, nv, nr, nc))


def _grid_order(Float, Y, nv, nr, nc):
    """:func:`synthesise`'s output, (t, l, s, v, r) flat, in the order (t, l, v, r, s):
    a transpose inside each (t, l) block, which stays in cache."""
    if nc == 1:
        return Y
    UInt = dr.uint32_array_t(Float)
    idx = dr.arange(UInt, dr.width(Y))
    block = idx // (nv * nr * nc)
    v = (idx // (nr * nc)) % nv
    r = (idx // nc) % nr
    s = idx % nc
    return dr.gather(Float, Y, block * (nv * nr * nc) + (s * nv + v) * nr + r)


#: Table polar angles are theta = (pi/2) sin(A x) / sin(A), x uniform in [0, 1]:
#: near grazing, where Fresnel transmittance and masking change fastest, the
#: spacing is cos(A) = 0.17 times the spacing at the pole.
TABLE_WARP = 1.4


def table_theta_of_x(x):
    return (0.5 * math.pi / math.sin(TABLE_WARP)) * np.sin(TABLE_WARP * np.asarray(x))


def table_x_of_theta(theta):
    """Inverse of :func:`table_theta_of_x` (Dr.Jit arrays)."""
    return dr.asin(theta * (math.sin(TABLE_WARP) / (0.5 * math.pi))) * (1.0 / TABLE_WARP)


#: Table azimuths are phi = pi sin(B x) / sin(B), x uniform in [0, 1]: near
#: forward scattering (phi = pi), where a large kappa makes the body term of
#: grazing directions fall steeply (light must leave through a facet near the
#: one it entered by, and the facets that both grazing directions see shrink to
#: a band), the spacing is cos(B) = 0.12 times the spacing at phi = 0.
PHI_WARP = 1.45


def table_phi_of_x(x):
    return (math.pi / math.sin(PHI_WARP)) * np.sin(PHI_WARP * np.asarray(x))


def table_x_of_phi(phi):
    """Inverse of :func:`table_phi_of_x` (Dr.Jit arrays)."""
    return dr.asin(phi * (math.sin(PHI_WARP) / math.pi)) * (1.0 / PHI_WARP)


def table_angles(n_theta, n_phi):
    """Table nodes: theta in [0, pi/2] (both ends, warped), phi in [0, pi] (both ends, warped)."""
    x = lambda n: np.linspace(0.0, 1.0, n)
    return table_theta_of_x(x(n_theta)), table_phi_of_x(x(n_phi))


def grazing_factors(dist, eta, grid, theta, nodes=None):
    """(F, d) at polar angles ``theta``: the body matrix at kappa = 0, per direction.

    At kappa = 0 the coupling is constant and the body matrix factorises:
    M = A(V) A(L)^T / Z with A(w) = sum_p a_p(w) / P(w) (the incident side
    b_q gives the same two non-zero channels as the exit side a_p; the third
    sums to zero over the mirror-symmetric node azimuths).  F = A_0 is the
    microfacet-averaged Fresnel transmittance over the projected area, which
    carries the steep fall of the body term towards grazing (Fresnel
    transmission, masking); d = A_1 / A_0 is the DoLP of light leaving at
    that angle (Fresnel transmission's T-/T+, averaged).  :func:`body_tables`
    divides these 1-D factors out of what it tabulates, so that the 3-D tables
    hold only the smooth coupling between the two directions.  ``nodes``
    (:func:`polar_nodes`): if already computed.
    """
    Float = dist.Float
    UInt = dr.uint32_array_t(Float)
    th_j, w_j = nodes if nodes is not None else polar_nodes(dist, grid)
    J, K = grid.n_theta, grid.n_phi // 2  # the azimuths phi_k and -phi_k give the same channels 0, 1
    theta = Float(theta)
    n = dr.width(theta)
    idx = dr.arange(UInt, n * J * K)
    i, j, k = idx // (J * K), (idx // K) % J, idx % K
    thn = dr.gather(Float, th_j, j)
    phn = (Float(k) + 0.5) * (2.0 * math.pi / grid.n_phi)
    stn = dr.sin(thn)
    node = (stn * dr.cos(phn), stn * dr.sin(phn), dr.cos(thn))
    a = transmitted(Float, eta, dr.gather(Float, theta, i), Float(0.0), node, dr.gather(Float, w_j, j), False)
    dr.eval(a[0], a[1])  # one kernel for both channels (each block_sum would evaluate its own)
    s0, s1 = dr.block_sum(a[0], J * K), dr.block_sum(a[1], J * K)
    return 2.0 * s0 / dist.projected_area(theta), s1 / dr.maximum(s0, 1e-30)


#: The tabulated channels, in the order of :func:`body_tables`: log M00 less
#: the grazing factors, then the other elements of the 3 x 3 block row by row,
#: as ratios to M00 less their kappa = 0 values.
CHANNELS = ("log_m00", "r01", "r02", "r10", "r11", "r12", "r20", "r21", "r22")


def body_tables(dist, eta, kappa, grid, polarized=True, planar=False):
    """The body term as an interpolation table over (x(phi), x(theta_L), x(theta_V)).

    M is divided by k_b cos(theta_L) and expressed in the bases of
    :func:`body_grid_matrices`; then the 1-D grazing factors of
    :func:`grazing_factors` (F and d, the kappa = 0 factorisation) are taken
    out, so that what is tabulated stays smooth where M itself falls steeply:

    factors: (log F, d) on ``grid.n_factor`` nodes of x(theta);
    table: on ``grid.table`` nodes, the nine channels of :data:`CHANNELS`:
    log M00 - log F(theta_L) - log F(theta_V), and M_ij / M00 for the other
    eight elements less their kappa = 0 values (d(theta_L) for M01,
    d(theta_V) for M10, d(theta_V) d(theta_L) for M11, zero for the rest);
    only the first channel when not ``polarized``.  At kappa = 0 the first
    channel is a constant and all the others vanish.  Logarithm and ratios vary
    more smoothly than the elements (a large kappa makes M00 peaked).  One table
    for all nine channels: eval computes one set of interpolation weights and
    reads each corner's texel from one place (interp.py).  ``planar``: the
    table channel-major, which is what the compact copy is packed from fastest.
    Returns (table, factors): :class:`TetraTable` and :class:`LineTable`.
    """
    Float = dist.Float
    UInt = dr.uint32_array_t(Float)
    nodes = polar_nodes(dist, grid)
    khat = coupling_modes(dist, kappa, grid, *nodes)
    th, ph = table_angles(*grid.table)
    th_f = table_theta_of_x(np.linspace(0.0, 1.0, grid.n_factor))
    # the grazing factors at the 1-D nodes and at the table's polar nodes, in one pass
    f_all, d_all = grazing_factors(dist, eta, grid, np.concatenate([th_f, th]), nodes)
    nf, n1 = len(th_f), len(th)
    logf_all = dr.log(dr.maximum(f_all, 1e-30))
    pick = lambda x, start, n: dr.gather(Float, x, dr.arange(UInt, n) + start)
    k = dr.arange(UInt, 2 * nf)
    factors = LineTable(dr.select(k % 2 == 0, dr.gather(Float, logf_all, k // 2), dr.gather(Float, d_all, k // 2)),
                        (nf, 2))
    logf1, d1 = pick(logf_all, nf, n1), pick(d_all, nf, n1)

    n3 = 3 if polarized else 1
    nc, nt = n3 * n3, len(ph)
    p = dist.projected_area(Float(th))
    series = body_series(dist, eta, kappa, grid, th, th, tuple(range(n3)), tuple(range(n3)), nodes, khat, (p, p))
    Y = synthesise(Float, grid, series, ph).array  # (t, l, s, v, r): rows r, columns s of the 3 x 3 block
    n = nt * n1 * n1

    def value(c, y, m00, l, v):
        """Channel c (an int, or an array) from element y and M00 of texels (., l, v)."""
        log_part = dr.log(m00) - dr.gather(Float, logf1, l) - dr.gather(Float, logf1, v)
        if not polarized:
            return log_part
        dl, dv = dr.gather(Float, d1, l), dr.gather(Float, d1, v)
        kappa0 = dr.select(c == 1, dl, dr.select(c == 3, dv, dr.select(c == 4, dl * dv, 0.0)))
        return dr.select(c == 0, log_part, y / m00 - kappa0)

    def planar_channels(count):
        """Channels 0 .. count - 1 (c = 3 r + s) of every texel (t, l, v), each its own array,
        read from Y in its own order (what the channels share traced once)."""
        texel = dr.arange(UInt, n)
        tl, v = texel // n1, texel % n1
        block = tl * (n3 * n1 * n3) + v * n3  # element (0, 0); the texel's others lie in one (t, l) block
        m00 = dr.maximum(dr.gather(Float, Y, block), 1e-30)
        l = tl % n1
        out = [dr.log(m00) - dr.gather(Float, logf1, l) - dr.gather(Float, logf1, v)]
        if count > 1:
            dl, dv = dr.gather(Float, d1, l), dr.gather(Float, d1, v)
            kappa0 = {1: dl, 3: dv, 4: dl * dv}
            for c in range(1, count):
                y = dr.gather(Float, Y, block + (c % n3) * (n1 * n3) + c // n3)
                out.append(y / m00 - kappa0.get(c, 0.0))
        return out

    shape = (nt, n1, n1, nc)
    if nc == 1 or planar:  # one array per channel, in one kernel
        channels = planar_channels(nc)
        dr.eval(*channels)
        return TetraTable(channels if nc > 1 else channels[0], shape), factors
    # a texel's channels side by side: the elements' transpose inside each (t, l) block, then the
    # channels element by element (gathers only, which forward-mode AD differentiates cheaply)
    orient = TetraTable(planar_channels(1)[0], shape[:3] + (1,)).orient  # from channel 0's own array
    y = _grid_order(Float, Y, n1, n3, n3)
    dr.eval(y)  # read twice below
    k = dr.arange(UInt, n * nc)
    tl, v, c = k // (n1 * nc), (k // nc) % n1, k % nc
    m00 = dr.maximum(dr.gather(Float, y, k - c), 1e-30)
    return TetraTable(value(c, y, m00, tl % n1, v), shape, orient), factors
