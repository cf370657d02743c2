"""Where the body term's error at one material and one direction pair comes from.

Splits the plugin's error against the brute-force reference (tests/reference.py)
into the quadrature's and the table's parts, for the body intensity M00:

* direct: the dense double sum over the package's microfacet nodes at the exact
  angles (fmbrdf_mi.model.body_direct), against the reference;
* series: the Fourier series the tables are built from (body_grid_matrices) at
  the exact angles: between node azimuths it is the trigonometric interpolant
  of the direct sums, so it may differ from them;
* table: the plugin's table lookup against that series (interpolation only);

then the same quadrature parts with more node azimuths (--n-phi) and the
table's part with other table resolutions (--table).

    python tools/check_point.py --material 3 1.5707963 0.4 100 --angles 84.6 82.3 164.9 \\
        --n-phi 128 256 --table 65 129 --table 97 81
"""
import argparse
import math

import numpy as np

from _common import directions, eval_mueller


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--material", type=float, nargs=4, required=True, metavar=("ETA", "ALPHA", "BETA", "KAPPA"))
    ap.add_argument("--angles", type=float, nargs=3, required=True, metavar=("THETA_L", "THETA_V", "PHI"),
                    help="degrees; phi = phi_V - phi_L")
    ap.add_argument("--n-phi", type=int, nargs="*", default=[], help="also these numbers of node azimuths")
    ap.add_argument("--table", type=int, nargs=2, action="append", default=[], metavar=("N_THETA", "N_PHI"),
                    help="also the table part with this table resolution (repeatable)")
    args = ap.parse_args()

    import mitsuba as mi
    mi.set_variant("llvm_ad_mono_polarized")
    import fmbrdf_mi  # noqa: F401
    from fmbrdf_mi.model.body import BodyGrid, body_grid_matrices
    from fmbrdf_mi.model.body_direct import body_matrices
    from reference import Reference

    eta, alpha, beta, kappa = args.material
    tl, tv, ph = args.angles
    L, V = directions(np.array([tl]), np.array([0.0])), directions(np.array([tv]), np.array([ph]))
    bsdf = mi.load_dict({"type": "fmbrdf", "eta": eta, "alpha": alpha, "beta": beta, "kappa": kappa,
                         "k_s": 1.0, "k_b": 1.0})
    M, x_in, x_out = eval_mueller(bsdf, L, V, component=1)
    ref = Reference(eta, alpha, beta, kappa, 128, 256).body([(L[0], V[0], x_in[0], x_out[0])])[0, 0, 0]
    angles = np.radians([tl]), np.radians([tv]), np.radians([ph])
    cos_l = math.cos(angles[0][0])  # the package's matrices are divided by k_b cos(theta_L)

    def quadrature(grid):
        direct = float(np.asarray(body_matrices(bsdf.dist, bsdf.eta, bsdf.kappa, grid, *angles)).ravel()[0])
        series = float(np.asarray(body_grid_matrices(bsdf.dist, bsdf.eta, bsdf.kappa, grid, *angles)).ravel()[0])
        return direct * cos_l, series * cos_l

    def table_part(series):
        m00, _, _ = bsdf.body_ratios(*(mi.Float(x) for x in (np.cos(angles[0]), np.cos(angles[1]), angles[2])))
        return float(np.asarray(m00)[0]) * cos_l / series - 1

    grid = bsdf.grid
    direct, series = quadrature(grid)
    print(f"material eta {eta} alpha {alpha} beta {beta} kappa {kappa}; theta_L {tl}, theta_V {tv}, phi {ph} deg")
    print(f"plugin / reference - 1: {M[0, 0, 0] / ref - 1:+.2e}")
    print(f"{grid.n_phi} node azimuths: direct / reference - 1 {direct / ref - 1:+.2e}, "
          f"series / reference - 1 {series / ref - 1:+.2e}")
    print(f"table {grid.table[0]}x{grid.table[0]}x{grid.table[1]}: table / series - 1 {table_part(series):+.2e}")
    for n_phi in args.n_phi:
        d, s = quadrature(BodyGrid(grid.n_theta, n_phi, grid.table, grid.n_factor))
        print(f"{n_phi} node azimuths: direct / reference - 1 {d / ref - 1:+.2e}, series / reference - 1 {s / ref - 1:+.2e}")
    for nt, nph in args.table:
        bsdf.grid = BodyGrid(grid.n_theta, grid.n_phi, (nt, nph), grid.n_factor)
        bsdf._rebuild()
        print(f"table {nt}x{nt}x{nph}: table / series - 1 {table_part(series):+.2e}")


if __name__ == "__main__":
    main()
