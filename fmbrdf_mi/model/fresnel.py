"""Fresnel reflectance and transmittance of a dielectric facet (paper, sec. 4.2-4.3).

The Mueller matrices are expressed in the s/p basis: the Stokes x-axis is the
s direction (perpendicular to the plane of incidence), so s1 > 0 means light
polarised perpendicular to that plane.  This is the basis Mitsuba's
``mueller.specular_reflection`` uses, and its sign of the phase term
``cos(delta)`` (-1 below Brewster's angle) is the paper's.
"""
import drjit as dr


def fresnel_amplitudes(cos_theta, eta):
    """Signed amplitude coefficients (r_s, r_p) for incidence from air onto IOR ``eta`` > 1.

    ``cos_theta`` is clamped to [0, 1]; Snell's law gives the refracted angle.
    """
    c = dr.clip(cos_theta, 0.0, 1.0)
    ct = dr.safe_sqrt(1.0 - (1.0 - c * c) / (eta * eta))
    return (c - eta * ct) / (c + eta * ct), (eta * c - ct) / (eta * c + ct)


def fresnel_rs_rp(cos_theta, eta):
    """Intensity reflectances (R_s, R_p)."""
    rs, rp = fresnel_amplitudes(cos_theta, eta)
    return rs * rs, rp * rp


def reflection_mueller_terms(cos_theta, eta):
    """(R+, R-, R_x cos delta) of the reflection Mueller matrix R(theta) (sec. 4.2).

    R = [[R+, R-, 0, 0], [R-, R+, 0, 0], [0, 0, Rc, 0], [0, 0, 0, Rc]].
    R_s R_p >= 0 always and r_s r_p changes sign at Brewster's angle, so
    Rc = R_x cos delta = r_s r_p with the signed amplitude coefficients.
    """
    rs, rp = fresnel_amplitudes(cos_theta, eta)
    Rs, Rp = rs * rs, rp * rp
    return 0.5 * (Rs + Rp), 0.5 * (Rs - Rp), rs * rp


def transmission_mueller_terms(cos_theta, eta):
    """(T+, T-) of the transmission Mueller matrix T(theta) (sec. 4.3), T = 1 - R.

    Only the first row/column of T enters the body term, because the
    depolariser D_p keeps intensity alone.
    """
    Rs, Rp = fresnel_rs_rp(cos_theta, eta)
    Ts, Tp = 1.0 - Rs, 1.0 - Rp
    return 0.5 * (Ts + Tp), 0.5 * (Ts - Tp)
