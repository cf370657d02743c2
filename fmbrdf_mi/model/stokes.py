"""Stokes-frame geometry shared by the surface and body terms.

Convention (Mitsuba 3's): a Stokes vector travelling along ``forward`` is
expressed in a basis whose x-axis is a unit vector ``x`` perpendicular to it,
with y = forward x x.  Changing the basis from ``x_cur`` to ``x_new`` is the
rotator of the signed angle from ``x_cur`` to ``x_new`` about ``forward``:
s1' = c s1 + s s2, s2' = -s s1 + c s2 with (c, s) = (cos 2t, sin 2t).
"""
import drjit as dr


def basis_rotation(forward, x_cur, x_new):
    """(cos 2t, sin 2t) of the rotator taking ``x_cur`` to ``x_new`` about ``forward``.

    Both bases must be unit vectors perpendicular to ``forward``.  Computed
    from the cosine and the signed sine of t, without trigonometric calls.
    """
    c = dr.dot(x_cur, x_new)
    s = dr.dot(forward, dr.cross(x_cur, x_new))
    return c * c - s * s, 2.0 * c * s


def perp_axis(axis, forward, fallback):
    """Unit vector along ``axis`` x ``forward``, or ``fallback`` where they are parallel.

    ``axis`` x ``forward`` is perpendicular to the plane holding both vectors:
    the s direction of a plane of incidence.
    """
    v = dr.cross(axis, forward)
    n2 = dr.squared_norm(v)
    ok = n2 > 1e-14
    return dr.select(ok, v * dr.rsqrt(dr.select(ok, n2, 1.0)), fallback)
