"""Brute-force NumPy reference of the FMBRDF (paper sec. 3-4), used only by tests and tools.

Written independently of the package: explicit 4x4 Mueller matrices, rotation
angles from atan2, a different quadrature (midpoint rule in theta = t_cut s^2
and in phi), Smith's Lambda by 2D quadrature rather than a closed-form
azimuthal integral, float64 throughout.  It is slow on purpose.

Frames: the macro normal is N = (0, 0, 1); L points to the light, V to the
viewer.  The incident Stokes vector travels along -L in a basis with x-axis
``x_in`` (perpendicular to L); the outgoing one along V with x-axis ``x_out``.
The y-axis of a basis is forward x x (Mitsuba 3's convention).
"""
import numpy as np


def rotator(t):
    c, s = np.cos(2 * t), np.sin(2 * t)
    M = np.zeros(np.shape(t) + (4, 4))
    M[..., 0, 0] = 1
    M[..., 3, 3] = 1
    M[..., 1, 1] = c
    M[..., 1, 2] = s
    M[..., 2, 1] = -s
    M[..., 2, 2] = c
    return M


def basis_angle(forward, x_from, x_to):
    """Signed angle about ``forward`` from basis vector x_from to x_to."""
    y_from = np.cross(forward, x_from)
    return np.arctan2(np.sum(x_to * y_from, -1), np.sum(x_to * x_from, -1))


def fresnel_amplitudes(cos_t, eta):
    cos_t = np.clip(cos_t, 0, 1)
    sin_t2 = (1 - cos_t ** 2) / eta ** 2
    ct = np.sqrt(1 - sin_t2)
    rs = (cos_t - eta * ct) / (cos_t + eta * ct)
    rp = (eta * cos_t - ct) / (eta * cos_t + ct)
    return rs, rp


def reflection_matrix(cos_t, eta):
    """Paper's R(theta): cos(delta) = -1 below Brewster's angle, +1 above."""
    rs, rp = fresnel_amplitudes(cos_t, eta)
    Rs, Rp = rs ** 2, rp ** 2
    brewster = np.arctan(eta)
    cos_delta = np.where(np.arccos(np.clip(cos_t, 0, 1)) < brewster, -1.0, 1.0)
    M = np.zeros(np.shape(cos_t) + (4, 4))
    M[..., 0, 0] = M[..., 1, 1] = (Rs + Rp) / 2
    M[..., 0, 1] = M[..., 1, 0] = (Rs - Rp) / 2
    M[..., 2, 2] = M[..., 3, 3] = np.sqrt(Rs * Rp) * cos_delta
    return M


def transmission_matrix(cos_t, eta):
    rs, rp = fresnel_amplitudes(cos_t, eta)
    Ts, Tp = 1 - rs ** 2, 1 - rp ** 2
    M = np.zeros(np.shape(cos_t) + (4, 4))
    M[..., 0, 0] = M[..., 1, 1] = (Ts + Tp) / 2
    M[..., 0, 1] = M[..., 1, 0] = (Ts - Tp) / 2
    M[..., 2, 2] = M[..., 3, 3] = np.sqrt(Ts * Tp)
    return M


def s_axis(normal, forward):
    """Unit s direction for light travelling along ``forward`` hitting a facet ``normal``."""
    v = np.cross(normal, forward)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    fallback = np.cross(forward, np.where(np.abs(forward[..., :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
    fallback = fallback / np.linalg.norm(fallback, axis=-1, keepdims=True)
    return np.where(n > 1e-12, v / np.maximum(n, 1e-300), fallback)


class Reference:
    """The model for one parameter set, by brute force."""

    def __init__(self, eta, alpha, beta, kappa, n_s=96, n_phi=192, tail=36.0):
        self.eta, self.alpha, self.beta, self.kappa = eta, alpha, beta, kappa
        self.t_cut = min(np.pi / 2, alpha * tail ** (1 / beta))
        # midpoint rule in s, theta = t_cut s^2 clusters nodes at the pole
        s = (np.arange(n_s) + 0.5) / n_s
        th = self.t_cut * s ** 2
        dth = self.t_cut * 2 * s / n_s
        ph = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
        TH, PH = np.meshgrid(th, ph, indexing="ij")
        dA = (dth * np.sin(th))[:, None] * (2 * np.pi / n_phi) * np.ones_like(PH)
        self.n = np.stack([np.sin(TH) * np.cos(PH), np.sin(TH) * np.sin(PH), np.cos(TH)], -1).reshape(-1, 3)
        shape = np.exp(-(TH / alpha) ** beta).reshape(-1)
        self.dA = dA.reshape(-1)
        self.c = 1.0 / np.sum(shape * self.n[:, 2] * self.dA)
        self.D = self.c * shape
        self.wD = self.D * self.dA            # D(n) d omega_n
        self._Kcols = None

    def D_of(self, cos_t):
        th = np.arccos(np.clip(cos_t, -1, 1))
        return np.where(cos_t > 0, self.c * np.exp(-(th / self.alpha) ** self.beta), 0.0)

    def G1(self, w):
        """Smith masking 1/(1 + Lambda), Lambda by 2D quadrature on the node set."""
        proj = np.sum(np.maximum(self.n @ w, 0) * self.wD)
        return w[2] / proj if w[2] > 0 else 0.0

    # ---------------------------------------------------------------- surface
    def surface(self, L, V, x_in, x_out, k_s=1.0):
        """Surface Mueller matrix k_s D G / (4 N.V) C R C (section 4.2), times nothing else.

        Equals Mitsuba's eval (BRDF x cos theta_L).
        """
        H = (L + V) / np.linalg.norm(L + V)
        cos_d = L @ H
        R = reflection_matrix(cos_d, self.eta)
        s_in = s_axis(H[None], -L[None])[0]
        s_out = s_axis(H[None], V[None])[0]
        R_in = rotator(basis_angle(-L, s_in, x_in))
        R_out = rotator(basis_angle(V, s_out, x_out))
        M = R_out @ R @ R_in.T
        scale = k_s * self.D_of(H[2]) * self.G1(L) * self.G1(V) / (4 * V[2])
        return scale * M

    # ---------------------------------------------------------------- body
    def _outgoing_vectors(self, V, x_out):
        """a(n) = D (V.n)+ C T(theta_o) e0 per node, times d omega (4-vectors)."""
        cos_o = self.n @ V
        T = transmission_matrix(cos_o, self.eta)
        s_f = s_axis(self.n, np.broadcast_to(V, self.n.shape))
        Rm = rotator(basis_angle(np.broadcast_to(V, self.n.shape), s_f, np.broadcast_to(x_out, self.n.shape)))
        a = np.einsum("nij,njk,k->ni", Rm, T, np.array([1.0, 0, 0, 0]))
        return a * (np.maximum(cos_o, 0) * self.wD)[:, None]

    def _incident_vectors(self, L, x_in):
        """b(n_i) = D (L.n_i)+ (e0^T T(theta_i) C)^T per node, times d omega."""
        cos_i = self.n @ L
        T = transmission_matrix(cos_i, self.eta)
        fwd = np.broadcast_to(-L, self.n.shape)
        s_f = s_axis(self.n, fwd)
        Rm = rotator(basis_angle(fwd, np.broadcast_to(x_in, self.n.shape), s_f))  # x_in basis -> facet basis
        b = np.einsum("i,nij,njk->nk", np.array([1.0, 0, 0, 0]), T, Rm)
        return b * (np.maximum(cos_i, 0) * self.wD)[:, None]

    def body(self, pairs, k_b=1.0, chunk=1024):
        """Body Mueller matrices (paper eq:observed body reflection Stokes vector) / E_o.

        ``pairs`` is a list of (L, V, x_in, x_out); returns an array (len(pairs), 4, 4).
        All pairs share one pass over the N^2 vMF coupling.
        """
        a = np.stack([self._outgoing_vectors(V, xo) for L, V, xi, xo in pairs], -1)  # (N, 4, P)
        b = np.stack([self._incident_vectors(L, xi) for L, V, xi, xo in pairs], -1)
        n = self.n
        N, P = len(n), len(pairs)
        a_flat = a.reshape(N, 4 * P)
        Ai = np.zeros((N, 4 * P))
        # Z(n_i) = int exp(kappa n.n_i) D(n) d omega_n; A(n_i) = int a(n) f(n, n_i) d omega_n
        for start in range(0, N, chunk):
            E = np.exp(self.kappa * (n @ n[start:start + chunk].T - 1.0))   # (N, chunk)
            Z = self.wD @ E
            Ai[start:start + chunk] = (a_flat.T @ E).T / Z[:, None]
        Ai = Ai.reshape(N, 4, P)
        out = np.einsum("nip,njp->pij", Ai, b)
        for k, (L, V, _, _) in enumerate(pairs):
            out[k] *= k_b / np.pi * self.G1(L) * self.G1(V) / V[2]
        return out
