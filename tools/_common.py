"""Helpers shared by the scripts in tools/ (and the tests): evaluate the BSDF on arrays, name the CPU."""
import os
import platform
import sys

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "tests"))


def directions(theta_deg, phi_deg):
    th, ph = np.radians(theta_deg), np.radians(phi_deg)
    return np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)


def eval_mueller(bsdf, L, V, component=None):
    """Mueller matrices (n, 4, 4) of ``bsdf.eval`` for light direction L and view V (local frame).

    Also returns Mitsuba's Stokes bases of -L and V, to hand to the reference.
    """
    import drjit as dr
    import mitsuba as mi

    n = len(L)
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = mi.Vector3f(np.ascontiguousarray(V.T, dtype=np.float32))
    wo = mi.Vector3f(np.ascontiguousarray(L.T, dtype=np.float32))
    if component is None:
        ctx = mi.BSDFContext()
    else:
        ctx = mi.BSDFContext(mi.TransportMode.Radiance, mi.BSDFFlags.All, component)
    M = bsdf.eval(ctx, si, wo)
    out = np.zeros((n, 4, 4))
    for i in range(4):
        for j in range(4):
            a = np.asarray(M[i, j])
            out[:, i, j] = a[0] if a.ndim == 2 else a  # first wavelength / channel
    x_in = np.asarray(mi.mueller.stokes_basis(-wo)).T
    x_out = np.asarray(mi.mueller.stokes_basis(si.wi)).T
    return out, x_in, x_out


def dolp(M):
    """DoLP of the light a Mueller matrix (n, 4, 4) reflects from unpolarised light."""
    return np.hypot(M[:, 1, 0], M[:, 2, 0]) / M[:, 0, 0]


def set_body_grid(bsdf, n_phi=None, table=None):
    """Rebuild ``bsdf``'s tables with ``n_phi`` node azimuths and the given
    (n_theta, n_phi) table resolution (None: keep the package's)."""
    if n_phi is None and table is None:
        return bsdf
    from fmbrdf_mi.model.body import BodyGrid
    g = bsdf.grid
    bsdf.grid = BodyGrid(g.n_theta, n_phi or g.n_phi, tuple(table or g.table), g.n_factor)
    bsdf._rebuild()
    return bsdf


def cpu_name():
    """The CPU's model name (for the header of a timing table)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"
