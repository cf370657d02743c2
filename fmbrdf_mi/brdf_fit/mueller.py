"""Mueller-matrix BRDF tables: the SCATMECH/NIST CSV layout and the package's plain table, in the package's frames.

A table holds, per row, the direction towards the light ``w_in`` and towards
the viewer ``w_out`` (unit vectors in the local frame, z = surface normal), the
Mueller BRDF f_ij (4 x 4, 1/sr) and optionally the wavelength (micrometres).
In memory (:class:`MuellerTable`) the matrix is always in **the package's
frames**: those of the ``fmbrdf`` plugin (fmbrdf_mi/bsdf.py), i.e. it maps a
Stokes vector of the incident light in Mitsuba's basis
``mi.mueller.stokes_basis(-w_in)`` to one of the reflected light in
``mi.mueller.stokes_basis(w_out)`` (:func:`stokes_basis` is the same
construction in NumPy), with Mitsuba's sign of S3.

**SCATMECH/NIST layout** (:func:`read_scatmech`).  A header line, then per row
``lambda`` (µm), ``thetai``, ``phi`` (incident azimuth), ``thetar``, ``phir``
(degrees), ``f_r11`` (1/sr, the unpolarised BRDF), then the 15 normalised
elements ``m12 ... m44`` (= f_rij / f_r11, row order), separated by commas,
tabs or blanks.  The directions are ``w = (sin t cos p, sin t sin p, cos t)``
with signed polar angles t in (-90, 90): a negative ``thetai`` with ``phi`` 0
is the source at azimuth 180 degrees (SCATMECH's ``BRDF_Model`` geometry, in
which the light propagates along (sin thetai, 0, -cos thetai) and
``phis`` = 0 is the forward direction).  The Stokes bases are SCATMECH's
``psps`` system (its default, ``BRDF_Model::Mueller``; ``GetBasisVectorsSP``):
for each propagation direction k a right-handed {s, p, k} with
s = z x k / |z x k| (perpendicular to the plane of k and the normal; (0, 1, 0)
along the normal) and p = k x s, so the planes of incidence and of exit for
the incident and the scattered light; S1 = |E_s|^2 - |E_p|^2,
S2 = 2 Re(E_s* E_p) and S3 = 2 Im(E_s* E_p), in which the Jones vector (1, i)
is (1, 0, 0, 1) (SCATMECH's conventions page: exp(-i w t) fields, (1, i) left
circular).

**Conversion** (:func:`sp_to_package`): Mitsuba's basis vector x of a
direction and its y = k x x form the same right-handed pair as {s, p}, so the
linear part is a rotation of each basis about its propagation direction
(``mi.mueller.rotate_mueller_basis``: M' = R_out M R_in^T, the incident one
about k_in = -w_in).  S3 changes sign: Mitsuba's circular convention is
Chipman's (``mi.mueller.right_circular_polarizer`` passes (1, 0, 0, 1), right
circular meaning clockwise seen looking at the source, which is SCATMECH's
(1, 0, 0, -1)), and Mitsuba's own ``specular_reflection`` of a metal has
M23 = -M32 of the opposite sign to the Jones-derived matrix in SCATMECH's
convention (tests/test_mueller_table.py checks both).  So
M_package = R_out D M_sp D R_in^T with D = diag(1, 1, 1, -1).  For a surface
with no linear-circular coupling (M_i3 = M_3i = 0 for i < 3: a dielectric such
as FMBRDF's and pplastic's, with M33 unchanged by D) the sign of S3 does not
matter.

**Plain table** (:func:`read_plain`): NPZ arrays or CSV columns named
``w_in_x, w_in_y, w_in_z, w_out_x, w_out_y, w_out_z`` (NPZ: ``w_in``,
``w_out`` of shape (n, 3)) or ``theta_in, phi_in, theta_out, phi_out``
(degrees, the formula above), ``m00 ... m33`` (NPZ: ``mueller`` of shape
(n, 4, 4)), the absolute Mueller BRDF in 1/sr in the package's frames, and
optionally ``wavelength_um``.

Bad input (:class:`MuellerTableError`): a malformed row, missing or extra
columns, a non-finite value, an angle out of range, a Mueller matrix outside
the physical bounds (:func:`check_physical`), an empty wavelength: one line
naming the file, the row (the line number in a CSV, the index in an NPZ) and
the column.
"""
from __future__ import annotations

import dataclasses
import math
import os

import numpy as np

#: The columns of the SCATMECH/NIST layout, in order.
SCATMECH_COLUMNS = ("lambda", "thetai", "phi", "thetar", "phir", "f_r11") + tuple(
    f"m{i}{j}" for i in range(1, 5) for j in range(1, 5) if (i, j) != (1, 1))
#: The Mueller columns of the plain CSV.
PLAIN_MUELLER = tuple(f"m{i}{j}" for i in range(4) for j in range(4))
PLAIN_VECTORS = ("w_in_x", "w_in_y", "w_in_z", "w_out_x", "w_out_y", "w_out_z")
PLAIN_ANGLES = ("theta_in", "phi_in", "theta_out", "phi_out")
#: Default slack of the physical bounds on normalised elements (measurement noise).
PHYSICAL_TOLERANCE = 0.05
#: D = diag(1, 1, 1, -1): SCATMECH's S3 to Mitsuba's.
CIRCULAR_FLIP = np.diag([1.0, 1.0, 1.0, -1.0])


class MuellerTableError(ValueError):
    """A Mueller BRDF table that cannot be read: one line naming the file, row and column."""


@dataclasses.dataclass
class MuellerTable:
    """Rows of a Mueller BRDF table, in the package's frames (module docstring)."""

    path: str
    w_in: np.ndarray        # (n, 3) towards the light
    w_out: np.ndarray       # (n, 3) towards the viewer
    mueller: np.ndarray     # (n, 4, 4) Mueller BRDF, 1/sr, package frames
    wavelength: np.ndarray  # (n,) micrometres, NaN when the table has none
    rows: np.ndarray        # (n,) the row of each entry in its file (CSV line number or NPZ index)
    kind: str               # "scatmech" or "plain"

    def __len__(self):
        return len(self.w_in)

    @property
    def f_r11(self):
        """The unpolarised BRDF f_r11 = M00 (1/sr)."""
        return self.mueller[:, 0, 0]

    @property
    def normalised(self):
        """M / M00: (n, 4, 4)."""
        return self.mueller / self.mueller[:, :1, :1]

    def wavelengths(self):
        """The distinct wavelengths (µm), sorted; [nan] for a table without wavelengths."""
        if np.isnan(self.wavelength).all():
            return [math.nan]
        return sorted(set(float(v) for v in self.wavelength))

    def at_wavelength(self, wl):
        """The rows at wavelength ``wl`` (NaN: the table without wavelengths)."""
        mask = np.isnan(self.wavelength) if math.isnan(wl) else self.wavelength == wl
        return self.subset(mask)

    def subset(self, mask):
        return dataclasses.replace(self, w_in=self.w_in[mask], w_out=self.w_out[mask], mueller=self.mueller[mask],
                                   wavelength=self.wavelength[mask], rows=self.rows[mask])


# ----------------------------------------------------------------------------------------------- frames

def directions(theta_deg, phi_deg):
    """Unit vectors (sin t cos p, sin t sin p, cos t) of polar angles ``theta_deg`` (signed) and azimuths (deg)."""
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1)


def stokes_basis(k):
    """Mitsuba's Stokes basis vector x of propagation directions ``k`` (n, 3): the first vector of
    ``coordinate_system(k)`` (Duff et al. 2017's branchless frame), as ``mi.mueller.stokes_basis``."""
    k = np.asarray(k, dtype=np.float64)
    x, y, z = k[..., 0], k[..., 1], k[..., 2]
    sign = np.where(z >= 0, 1.0, -1.0)   # copysign(1, z); z = -0 does not occur for unit vectors here
    a = -1.0 / (sign + z)
    b = x * y * a
    return np.stack([1.0 + sign * x * x * a, sign * b, -sign * x], axis=-1)


def s_axis(k):
    """SCATMECH's s vector of propagation directions ``k`` (n, 3): z x k / |z x k|, (0, 1, 0) along z."""
    k = np.asarray(k, dtype=np.float64)
    s = np.stack([-k[..., 1], k[..., 0], np.zeros(k.shape[:-1])], axis=-1)
    n = np.linalg.norm(s, axis=-1, keepdims=True)
    pole = n[..., 0] <= 1e-10
    return np.where(pole[..., None], np.array([0.0, 1.0, 0.0]), s / np.where(pole[..., None], 1.0, n))


def basis_rotation(k, current, target):
    """Mueller matrices (n, 4, 4) re-expressing Stokes vectors of propagation ``k`` from basis vector
    ``current`` to ``target`` (both normal to k): Mitsuba's ``rotate_stokes_basis``, an angle t with
    cos t = current . target and sin t = k . (current x target), the rotator of angle 2t."""
    c = np.sum(current * target, axis=-1)
    s = np.sum(k * np.cross(current, target), axis=-1)
    c2, s2 = c * c - s * s, 2.0 * c * s
    R = np.zeros(c.shape + (4, 4))
    R[..., 0, 0] = R[..., 3, 3] = 1.0
    R[..., 1, 1] = R[..., 2, 2] = c2
    R[..., 1, 2], R[..., 2, 1] = s2, -s2
    return R


def _rotations(w_in, w_out):
    k_in, k_out = -np.asarray(w_in, dtype=np.float64), np.asarray(w_out, dtype=np.float64)
    R_in = basis_rotation(k_in, s_axis(k_in), stokes_basis(k_in))
    R_out = basis_rotation(k_out, s_axis(k_out), stokes_basis(k_out))
    return R_in, R_out


def sp_to_package(M, w_in, w_out):
    """Mueller matrices (n, 4, 4) in SCATMECH's psps bases to the package's frames (module docstring)."""
    R_in, R_out = _rotations(w_in, w_out)
    return R_out @ (CIRCULAR_FLIP @ M @ CIRCULAR_FLIP) @ np.swapaxes(R_in, -1, -2)


def package_to_sp(M, w_in, w_out):
    """The inverse of :func:`sp_to_package`."""
    R_in, R_out = _rotations(w_in, w_out)
    return CIRCULAR_FLIP @ (np.swapaxes(R_out, -1, -2) @ M @ R_in) @ CIRCULAR_FLIP


# ------------------------------------------------------------------------------------------------ checks

def check_physical(Mn, tolerance=PHYSICAL_TOLERANCE, base=1):
    """The first violation of the physical bounds of normalised Mueller matrices ``Mn`` (n, 4, 4): (row index,
    element name "mIJ" with indices from ``base`` (SCATMECH's 1, the plain table's 0), message) or None.  Bounds (each with ``tolerance`` of slack for noise):
    |m_ij| <= 1, diattenuation |(m12, m13, m14)| <= 1, polarizance |(m21, m31, m41)| <= 1, and
    sum m_ij^2 <= 4 (tr(M^T M) <= 4 m11^2 for any Mueller matrix)."""
    tol = float(tolerance)
    name = lambda i, j: f"m{i + base}{j + base}"
    big = np.abs(Mn) > 1.0 + tol
    if big.any():
        r, i, j = (int(v) for v in np.argwhere(big)[0])
        return r, name(i, j), f"|{name(i, j)}| = {abs(Mn[r, i, j]):.4g} > 1 (not a physical Mueller matrix)"
    checks = (("diattenuation", np.linalg.norm(Mn[:, 0, 1:], axis=1), name(0, 1)),
              ("polarizance", np.linalg.norm(Mn[:, 1:, 0], axis=1), name(1, 0)),
              ("sum of squared normalised elements / 4", np.sqrt(np.sum(Mn ** 2, axis=(1, 2)) / 4.0), name(0, 0)))
    for what, v, col in checks:
        bad = v > 1.0 + tol
        if bad.any():
            r = int(np.flatnonzero(bad)[0])
            return r, col, f"{what} {v[r]:.4g} > 1 (not a physical Mueller matrix)"
    return None


def _fail(path, row, column, msg):
    raise MuellerTableError(f"{path}: row {row}, column {column}: {msg}")


def _check_rows(path, rows, names, values, w_in, w_out, mueller, wavelength, tolerance):
    """The shared checks of both readers; raise at the first problem."""
    bad = ~np.isfinite(values)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        _fail(path, rows[r], names[c], f"{values[r, c]!r} is not a finite number")
    cols = (("thetai", "thetar") if "thetai" in names else ("theta_in", "theta_out") if "theta_in" in names
            else ("w_in_z", "w_out_z"))
    for w, cz, what in ((w_in, cols[0], "incidence"), (w_out, cols[1], "exit")):
        low = w[:, 2] <= 1e-6
        if low.any():
            r = int(np.flatnonzero(low)[0])
            _fail(path, rows[r], cz, f"{what} below or on the horizon (polar angle must be in (-90, 90) degrees, "
                                     f"z > 0)")
    if wavelength is not None:
        wl = wavelength
        neg = ~(wl > 0)
        if neg.any():
            r = int(np.flatnonzero(neg)[0])
            _fail(path, rows[r], "lambda" if "lambda" in names else "wavelength_um",
                  f"wavelength {wl[r]:g} must be > 0 (micrometres)")
    m00 = mueller[:, 0, 0]
    neg = ~(m00 > 0)
    if neg.any():
        r = int(np.flatnonzero(neg)[0])
        _fail(path, rows[r], "f_r11" if "f_r11" in names else "m00", f"unpolarised BRDF {m00[r]:g} must be > 0 (1/sr)")
    v = check_physical(mueller / m00[:, None, None], tolerance, base=0 if "m00" in names else 1)
    if v is not None:
        r, col, msg = v
        _fail(path, rows[r], col, msg + f", beyond the tolerance {tolerance:g}")


def _angle_ranges(path, rows, names, values, columns):
    for name, lo, hi in columns:
        c = names.index(name)
        v = values[:, c]
        out = ~((v > lo) & (v < hi)) if "theta" in name else ~((v >= lo) & (v <= hi))
        if out.any():
            r = int(np.flatnonzero(out)[0])
            rng = f"({lo:g}, {hi:g})" if "theta" in name else f"[{lo:g}, {hi:g}]"
            _fail(path, rows[r], name, f"{v[r]:g} degrees is out of range {rng}")


# ------------------------------------------------------------------------------------------------ CSV text

def _split(line, sep):
    return [t.strip() for t in (line.split(sep) if sep else line.split())]


def _read_text(path):
    """(header names, line numbers, values (n, k) float64) of a delimited text table with one header line."""
    path = os.fspath(path)
    with open(path, encoding="utf-8", errors="replace") as f:
        lines = f.read().splitlines()
    body = [(k + 1, ln) for k, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith("#")]
    if not body:
        raise MuellerTableError(f"{path}: empty file: expected a header line and rows")
    (hline, header), rest = body[0], body[1:]
    sep = "," if "," in header else "\t" if "\t" in header else None
    names = [t.lower() for t in _split(header, sep)]
    if not rest:
        raise MuellerTableError(f"{path}: no rows after the header (line {hline})")
    rows, values = [], []
    for ln, text in rest:
        toks = _split(text, sep)
        if sep and toks and toks[-1] == "":
            toks = toks[:-1]   # a trailing separator
        if len(toks) != len(names):
            column = names[len(toks)] if len(toks) < len(names) else f"{len(toks)} (extra)"
            raise MuellerTableError(f"{path}: row {ln}, column {column}: {len(toks)} values, the header has "
                                    f"{len(names)} ({', '.join(names[:6])}, ...)")
        row = []
        for name, t in zip(names, toks):
            try:
                row.append(float(t))
            except ValueError:
                what = "empty" if not t else f"{t!r} is not a number"
                raise MuellerTableError(f"{path}: row {ln}, column {name}: {what}") from None
        rows.append(ln)
        values.append(row)
    return names, np.asarray(rows), np.asarray(values, dtype=np.float64)


def read_scatmech(path, tolerance=PHYSICAL_TOLERANCE):
    """A SCATMECH/NIST CSV table (module docstring) as a :class:`MuellerTable` in the package's frames.
    The header line's names are not checked (files differ in their spelling); its number of columns is."""
    path = os.fspath(path)
    names, rows, values = _read_text(path)
    if len(names) != len(SCATMECH_COLUMNS):
        raise MuellerTableError(f"{path}: row 1, column {len(names)}: the header has {len(names)} columns; the "
                                f"SCATMECH layout has {len(SCATMECH_COLUMNS)} ({', '.join(SCATMECH_COLUMNS[:6])}, "
                                f"m12 ... m44)")
    names = list(SCATMECH_COLUMNS)
    return _scatmech_rows(path, names, rows, values, tolerance)


def _scatmech_rows(path, names, rows, values, tolerance):
    bad = ~np.isfinite(values)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        _fail(path, rows[r], names[c], f"{values[r, c]!r} is not a finite number")
    _angle_ranges(path, rows, names, values, (("thetai", -90, 90), ("thetar", -90, 90), ("phi", -360, 360),
                                              ("phir", -360, 360)))
    w_in = directions(values[:, 1], values[:, 2])
    w_out = directions(values[:, 3], values[:, 4])
    f11 = values[:, 5]
    Mn = np.empty((len(values), 4, 4))
    Mn[:, 0, 0] = 1.0
    Mn.reshape(-1, 16)[:, 1:] = values[:, 6:]
    M_sp = Mn * f11[:, None, None]
    _check_rows(path, rows, names, values, w_in, w_out, M_sp, values[:, 0], tolerance)
    M = sp_to_package(M_sp, w_in, w_out)
    return MuellerTable(path, w_in, w_out, M, values[:, 0].copy(), rows, "scatmech")


def write_scatmech(path, w_in, w_out, mueller, wavelength_um):
    """Write a SCATMECH/NIST CSV (module docstring) from Mueller BRDFs ``mueller`` (n, 4, 4) in the package's
    frames; the angles are written as signed polar angles with azimuths in [0, 360)."""
    w_in, w_out = np.asarray(w_in, float), np.asarray(w_out, float)
    M_sp = package_to_sp(np.asarray(mueller, float), w_in, w_out)
    wl = np.broadcast_to(np.asarray(wavelength_um, float), (len(w_in),))

    def angles(w):
        t = np.degrees(np.arccos(np.clip(w[:, 2], -1, 1)))
        p = np.degrees(np.arctan2(w[:, 1], w[:, 0])) % 360.0
        return t, p

    ti, pi_ = angles(w_in)
    tr, pr = angles(w_out)
    f11 = M_sp[:, 0, 0]
    Mn = (M_sp / f11[:, None, None]).reshape(-1, 16)[:, 1:]
    data = np.column_stack([wl, ti, pi_, tr, pr, f11, Mn])
    tmp = os.fspath(path) + ".part"
    with open(tmp, "w") as f:
        f.write(",".join(SCATMECH_COLUMNS) + "\n")
        for row in data:
            f.write(",".join(repr(float(v)) for v in row) + "\n")
    os.replace(tmp, path)


# ---------------------------------------------------------------------------------------------- plain table

def read_plain(path, tolerance=PHYSICAL_TOLERANCE):
    """The package's plain table (module docstring), NPZ or CSV, as a :class:`MuellerTable`."""
    path = os.fspath(path)
    if path.lower().endswith(".npz"):
        return _read_plain_npz(path, tolerance)
    names, rows, values = _read_text(path)
    unknown = [n for n in names if n not in PLAIN_MUELLER + PLAIN_VECTORS + PLAIN_ANGLES + ("wavelength_um",)]
    if unknown:
        raise MuellerTableError(f"{path}: row 1, column {unknown[0]}: not a column of the plain table (valid: "
                                f"wavelength_um, w_in_x ... w_out_z or theta_in, phi_in, theta_out, phi_out, "
                                f"m00 ... m33)")
    missing = [n for n in PLAIN_MUELLER if n not in names]
    has_vec = all(n in names for n in PLAIN_VECTORS)
    has_ang = all(n in names for n in PLAIN_ANGLES)
    if missing or has_vec == has_ang:
        col = missing[0] if missing else "w_in_x"
        raise MuellerTableError(f"{path}: row 1, column {col}: the plain table needs m00 ... m33 and either "
                                f"w_in_x ... w_out_z or theta_in, phi_in, theta_out, phi_out (one of them)")
    col = {n: values[:, names.index(n)] for n in names}
    bad = ~np.isfinite(values)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        _fail(path, rows[r], names[c], f"{values[r, c]!r} is not a finite number")
    if has_vec:
        w_in = np.column_stack([col[n] for n in PLAIN_VECTORS[:3]])
        w_out = np.column_stack([col[n] for n in PLAIN_VECTORS[3:]])
        _unit(path, rows, w_in, "w_in_x")
        _unit(path, rows, w_out, "w_out_x")
    else:
        _angle_ranges(path, rows, names, values, (("theta_in", -90, 90), ("theta_out", -90, 90),
                                                  ("phi_in", -360, 360), ("phi_out", -360, 360)))
        w_in = directions(col["theta_in"], col["phi_in"])
        w_out = directions(col["theta_out"], col["phi_out"])
    M = np.stack([col[n] for n in PLAIN_MUELLER], axis=1).reshape(-1, 4, 4)
    wl = col.get("wavelength_um")
    _check_rows(path, rows, names, values, w_in, w_out, M, wl, tolerance)
    return MuellerTable(path, w_in, w_out, M, np.full(len(M), np.nan) if wl is None else wl.copy(), rows, "plain")


def _unit(path, rows, w, column):
    n = np.linalg.norm(w, axis=1)
    bad = np.abs(n - 1.0) > 1e-4
    if bad.any():
        r = int(np.flatnonzero(bad)[0])
        _fail(path, rows[r], column, f"direction of length {n[r]:.6g}; must be a unit vector")
    w /= n[:, None]


def _read_plain_npz(path, tolerance):
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: np.asarray(z[k]) for k in z.files}
    except (ValueError, OSError) as e:
        if isinstance(e, FileNotFoundError):
            raise
        raise MuellerTableError(f"{path}: row -, column -: not a readable NPZ file ({e})") from None
    allowed = {"w_in", "w_out", "theta_in", "phi_in", "theta_out", "phi_out", "mueller", "wavelength_um"}
    extra = sorted(set(data) - allowed)
    if extra:
        raise MuellerTableError(f"{path}: row -, column {extra[0]}: not an array of the plain table (valid: "
                                f"{', '.join(sorted(allowed))})")
    if "mueller" not in data:
        raise MuellerTableError(f"{path}: row -, column mueller: missing: an (n, 4, 4) array of Mueller BRDFs")
    M = data["mueller"].astype(np.float64)
    if M.ndim != 3 or M.shape[1:] != (4, 4) or len(M) == 0:
        raise MuellerTableError(f"{path}: row -, column mueller: shape {M.shape}; must be (n, 4, 4), n >= 1")
    n = len(M)
    rows = np.arange(n)
    has_vec = "w_in" in data and "w_out" in data
    has_ang = all(k in data for k in ("theta_in", "phi_in", "theta_out", "phi_out"))
    if has_vec == has_ang:
        raise MuellerTableError(f"{path}: row -, column w_in: give either w_in and w_out (n, 3) or theta_in, "
                                f"phi_in, theta_out, phi_out (n,) in degrees (one of them)")
    cols = ["w_in", "w_out"] if has_vec else ["theta_in", "phi_in", "theta_out", "phi_out"]
    for k in cols + (["wavelength_um"] if "wavelength_um" in data else []):
        want = (n, 3) if k in ("w_in", "w_out") else (n,)
        if data[k].shape != want:
            raise MuellerTableError(f"{path}: row -, column {k}: shape {data[k].shape}; must be {want}")
    flat = [M.reshape(n, 16)] + [data[k].reshape(n, -1).astype(np.float64) for k in cols]
    names = list(PLAIN_MUELLER) + [f"{k}" for k in cols for _ in range(data[k].reshape(n, -1).shape[1])]
    values = np.concatenate(flat, axis=1)
    wl = data["wavelength_um"].astype(np.float64) if "wavelength_um" in data else None
    if wl is not None:
        values = np.column_stack([values, wl])
        names.append("wavelength_um")
    bad = ~np.isfinite(values)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        _fail(path, rows[r], names[c], f"{values[r, c]!r} is not a finite number")
    if has_vec:
        w_in, w_out = data["w_in"].astype(np.float64), data["w_out"].astype(np.float64)
        _unit(path, rows, w_in, "w_in")
        _unit(path, rows, w_out, "w_out")
    else:
        ang = np.column_stack([data[k] for k in cols]).astype(np.float64)
        _angle_ranges(path, rows, cols, ang, (("theta_in", -90, 90), ("theta_out", -90, 90), ("phi_in", -360, 360),
                                              ("phi_out", -360, 360)))
        w_in, w_out = directions(ang[:, 0], ang[:, 1]), directions(ang[:, 2], ang[:, 3])
    _check_rows(path, rows, names, values, w_in, w_out, M, wl, tolerance)
    return MuellerTable(path, w_in, w_out, M, np.full(n, np.nan) if wl is None else wl, rows, "plain")


def write_plain(path, w_in, w_out, mueller, wavelength_um=None):
    """Write the plain table (NPZ by a ``.npz`` name, else CSV with the unit-vector columns)."""
    w_in, w_out, M = (np.asarray(a, float) for a in (w_in, w_out, mueller))
    path = os.fspath(path)
    if path.lower().endswith(".npz"):
        extra = {} if wavelength_um is None else {
            "wavelength_um": np.broadcast_to(np.asarray(wavelength_um, float), (len(M),)).copy()}
        tmp = path[:-4] + ".part.npz"
        np.savez(tmp, w_in=w_in, w_out=w_out, mueller=M, **extra)
        os.replace(tmp, path)
        return
    cols = list(PLAIN_VECTORS) + list(PLAIN_MUELLER)
    data = [w_in, w_out, M.reshape(-1, 16)]
    if wavelength_um is not None:
        cols = ["wavelength_um"] + cols
        data = [np.broadcast_to(np.asarray(wavelength_um, float), (len(M),))[:, None]] + data
    data = np.concatenate(data, axis=1)
    tmp = path + ".part"
    with open(tmp, "w") as f:
        f.write(",".join(cols) + "\n")
        for row in data:
            f.write(",".join(repr(float(v)) for v in row) + "\n")
    os.replace(tmp, path)


# ---------------------------------------------------------------------------------------------- dispatch

def is_mueller_table(path):
    """Whether ``path`` names a Mueller table by its extension (``.npz``, ``.csv``, ``.tsv``, ``.txt``, ``.dat``)."""
    return os.fspath(path).lower().endswith((".npz", ".csv", ".tsv", ".txt", ".dat"))


def read_table(path, tolerance=PHYSICAL_TOLERANCE):
    """A Mueller table of either layout: NPZ is the plain table; a text table whose header names ``m00`` is
    the plain CSV, any other the SCATMECH/NIST layout."""
    path = os.fspath(path)
    if path.lower().endswith(".npz"):
        return read_plain(path, tolerance)
    with open(path, encoding="utf-8", errors="replace") as f:
        head = ""
        for line in f:
            if line.strip() and not line.lstrip().startswith("#"):
                head = line.lower()
                break
    return read_plain(path, tolerance) if "m00" in head else read_scatmech(path, tolerance)
