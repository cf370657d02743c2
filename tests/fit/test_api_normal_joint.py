"""The joint material + normals refinement (fit/api/normal_joint.py, fit/solve/normal_system.py) and
`fmbrdf-mi fit --refine-normals` (fit/outputs/normals.py)."""
import json
import os

import numpy as np
import pytest

TRUE = {"eta": 1.45, "alpha": 0.25, "beta": 1.0, "kappa": 10.0, "k_s": 1.0, "r_k": 0.5}
LIGHTS = [(-0.5, 0.5, 1.0), (0.6, 0.2, 1.0), (0.1, -0.6, 0.8)]
POWERS = [1.0, 0.7, 1.2]


def _dense_system(pix, val, st, coef, t1, t2, w, ridge):
    """H_nn as a dense matrix, from the definitions (independent of NormalBlock's index tricks)."""
    N = len(t1)
    Jd = np.zeros((len(pix), 2 * N))
    for r in range(len(pix)):
        for q, p in enumerate(pix[r]):
            if p >= 0:
                Jd[r, 2 * p:2 * p + 2] += val[r, q]
    Jp = np.zeros((3 * len(st), 2 * N))
    for e, s in enumerate(st):
        for c, p in zip(coef, s):
            Jp[3 * e:3 * e + 3, 2 * p] += np.sqrt(w) * c * t1[p]
            Jp[3 * e:3 * e + 3, 2 * p + 1] += np.sqrt(w) * c * t2[p]
    return Jd, Jd.T @ Jd + Jp.T @ Jp + np.diag(ridge.ravel())


@pytest.mark.parametrize("prior", ["curvature", "membrane"])
def test_normal_block_and_schur_step_match_dense_algebra(prior):
    """NormalBlock's product, its CG solve and the Schur-complement step against
    dense NumPy on a 4 x 5 mask with a hole (random Jacobians; 2 x 2 bilinear stencils with fixed pixels),
    and the material's sandwich covariance against [H^-1 F H^-1]_mm formed densely.
    CG stops at a relative residual of 1e-10 on a system of condition < 1e4: 1e-6 relative is generous."""
    from fmbrdf_mi.fit.problem.normals import stencils
    from fmbrdf_mi.fit.problem.normals import tangent_bases
    from fmbrdf_mi.fit.solve.normal_system import NormalBlock, data_products, material_covariance, solve_step

    rng = np.random.default_rng(4)
    mask = np.ones((4, 5), bool)
    mask[1, 2] = False
    st, coef = stencils(mask, prior)
    N = int(mask.sum())
    # stencil count from the definition: pairs (membrane) or triples (curvature) along rows and columns
    L = len(coef)
    expect = sum(all(mask[y, x + k] for k in range(L)) for y in range(4) for x in range(5 - L + 1)) + \
        sum(all(mask[y + k, x] for k in range(L)) for y in range(4 - L + 1) for x in range(5))
    assert len(st) == expect
    n = rng.normal(size=(N, 3))
    n[:, 2] = np.abs(n[:, 2]) + 1
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    t1, t2 = tangent_bases(n)
    m, p = 60, 6
    pix = rng.integers(-1, N, size=(m, 4))
    val = rng.normal(size=(m, 4, 2))
    Jm = rng.normal(size=(m, p))
    r = rng.normal(size=m)
    w, mu = 0.7, 0.05
    blk = NormalBlock(pix, val, st, coef, t1, t2, w, mu)
    Jd, H = _dense_system(pix, val, st, coef, t1, t2, w, blk.ridge)
    x = rng.normal(size=(N, 2, 3))
    np.testing.assert_allclose(blk.apply(x).reshape(2 * N, 3), H @ x.reshape(2 * N, 3), rtol=1e-10, atol=1e-10)
    b = rng.normal(size=(N, 2, 2))
    np.testing.assert_allclose(blk.solve(b).reshape(2 * N, 2), np.linalg.solve(H, b.reshape(2 * N, 2)), rtol=1e-6,
                               atol=1e-8)
    Hmm, Hmn, gm, gn = data_products(pix, val, Jm, r, N)
    np.testing.assert_allclose(Hmn.reshape(p, 2 * N), Jm.T @ Jd, atol=1e-10)
    np.testing.assert_allclose(gn.ravel(), Jd.T @ r, atol=1e-10)
    dm, dn = solve_step(Hmm, Hmn, blk, gm, gn, mu)
    A = np.block([[Hmm + mu * np.diag(np.diag(Hmm)), Jm.T @ Jd], [Jd.T @ Jm, H]])
    ref = np.linalg.solve(A, -np.concatenate([gm, gn.ravel()]))
    np.testing.assert_allclose(np.concatenate([dm, dn.ravel()]), ref, rtol=1e-6, atol=1e-8)
    blk0 = NormalBlock(pix, val, st, coef, t1, t2, w, 0.0)
    _, H0 = _dense_system(pix, val, st, coef, t1, t2, w, blk0.ridge)
    # the sandwich: full H^-1 (with the prior) around the data's J^T J, material block
    Hfull = np.block([[Hmm, Jm.T @ Jd], [Jd.T @ Jm, H0]])
    Jfull = np.hstack([Jm, Jd])
    Hi = np.linalg.inv(Hfull)
    C = (Hi @ Jfull.T @ Jfull @ Hi)[:p, :p]
    np.testing.assert_allclose(material_covariance(Hmm, Hmn, blk0, Jm), C, rtol=1e-6, atol=1e-6 * np.abs(C).max())
    # without a prior the sandwich is the inverse Fisher information
    blk1 = NormalBlock(pix, val, st, coef, t1, t2, 0.0, 0.0)
    _, H1 = _dense_system(pix, val, st, coef, t1, t2, 0.0, blk1.ridge)
    H1full = np.block([[Hmm, Jm.T @ Jd], [Jd.T @ Jm, H1]])
    np.testing.assert_allclose(material_covariance(Hmm, Hmn, blk1, Jm), np.linalg.inv(H1full)[:p, :p], rtol=1e-5,
                               atol=1e-8)


def _apply_matrix_free(pix, val, st, coef, t1, t2, w, ridge, x):
    """H_nn x as NormalBlock.apply computed it before H_nn was assembled (commit 6dab7a8): matrix-free, with
    scatter-adds (np.add.at) over the data rows' terms and the prior's stencils."""
    ok = pix >= 0
    q = np.where(ok, pix, 0)
    v = np.where(ok[..., None], val, 0.0)
    jx = np.einsum("mqa,mqar->mr", v, x[q])
    y = np.zeros_like(x)
    np.add.at(y, q.ravel(), (v[:, :, :, None] * jx[:, None, None, :]).reshape(-1, 2, x.shape[2]))
    y += ridge[:, :, None] * x
    if len(st) and w:
        d = 0.0
        for s, c in enumerate(coef):
            k = st[:, s]
            d = d + c * (t1[k][:, :, None] * x[k, 0][:, None, :] + t2[k][:, :, None] * x[k, 1][:, None, :])
        d = w * d
        for s, c in enumerate(coef):
            k = st[:, s]
            g = np.stack([np.einsum("ec,ecr->er", t1[k], d), np.einsum("ec,ecr->er", t2[k], d)], 1)
            np.add.at(y, k, c * g)
    return y


@pytest.mark.parametrize("prior", ["curvature", "membrane"])
def test_assembled_normal_block_matches_the_matrix_free_product(prior):
    """NormalBlock.apply (H_nn assembled as 2 x 2 pair blocks) equals the matrix-free product it replaced, to
    rounding, on a 7 x 9 mask with holes: rows shaped like the refinement's (bilinear 2 x 2 corners, centre
    samples with one pixel 8 times, border rows with extrapolation terms i and the pixel opposite, -1 fixed
    corners), several right-hand sides; also without the prior, with a second block on the same pattern (the
    kept pattern) and on another.  data_products against its scatter-add definition."""
    from fmbrdf_mi.fit.problem.normals import stencils, tangent_bases
    from fmbrdf_mi.fit.solve.normal_system import NormalBlock, data_products

    rng = np.random.default_rng(7)
    mask = np.ones((7, 9), bool)
    mask[2, 3] = mask[4, 6] = mask[0, 0] = False
    st, coef = stencils(mask, prior)
    N = int(mask.sum())
    pos = -np.ones(mask.shape, int)
    pos[mask] = np.arange(N)
    ys, xs = np.nonzero(mask)

    def rows(kind):
        out = []
        for y, x in zip(ys, xs):
            i = pos[y, x]
            dy, dx = rng.choice([-1, 1], 2)
            corners = [pos[y + a, x + b] if 0 <= y + a < 7 and 0 <= x + b < 9 else -1
                       for a, b in ((0, 0), (0, dx), (dy, 0), (dy, dx))]
            out.append([i] * 8)                                          # a sample at the centre
            r = []
            for a, b, c in zip((0, 0, dy, dy), (0, dx, 0, dx), corners):
                if c >= 0 or kind == "fixed":
                    r += [c, c]
                else:                                                    # extrapolated: i and the pixel opposite
                    yo, xo = y - a, x - b
                    r += [i, pos[yo, xo] if 0 <= yo < 7 and 0 <= xo < 9 else -1]
            out.append(r)
        return np.array(out)

    for kind in ("extrapolated", "fixed"):
        pix = rows(kind)
        pix = np.concatenate([pix, pix])                                 # two lights: the same pixel lists
        assert (pix < 0).any() and any(len(set(r)) < 8 for r in pix)
        n = rng.normal(size=(N, 3))
        n[:, 2] = np.abs(n[:, 2]) + 1
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        t1, t2 = tangent_bases(n)
        for w, mu in ((0.7, 0.05), (3.0, 0.0), (0.0, 0.0)):      # the 2nd on the 1st one's pattern
            val = rng.normal(size=pix.shape + (2,))
            blk = NormalBlock(pix, val, st, coef, t1, t2, w, mu)
            for R in (1, 4):
                x = rng.normal(size=(N, 2, R))
                ref = _apply_matrix_free(pix, val, st, coef, t1, t2, w, blk.ridge, x)
                np.testing.assert_allclose(blk.apply(x), ref, rtol=0, atol=1e-12 * np.abs(ref).max())
        m, p = len(pix), 6
        Jm, r = rng.normal(size=(m, p)), rng.normal(size=m)
        Hmm, Hmn, gm, gn = data_products(pix, val, Jm, r, N)
        ok = pix >= 0
        q, v = np.where(ok, pix, 0), np.where(ok[..., None], val, 0.0)
        Hmn_ref, gn_ref = np.zeros((N, 2, p)), np.zeros((N, 2))
        np.add.at(Hmn_ref, q.ravel(), (v[:, :, :, None] * Jm[:, None, None, :]).reshape(-1, 2, p))
        np.add.at(gn_ref, q.ravel(), (v * r[:, None, None]).reshape(-1, 2))
        np.testing.assert_allclose(Hmn, Hmn_ref.transpose(2, 0, 1), rtol=1e-14, atol=1e-14)
        np.testing.assert_allclose(gn, gn_ref, rtol=1e-14, atol=1e-14)
        np.testing.assert_allclose(Hmm, Jm.T @ Jm)
        np.testing.assert_allclose(gm, Jm.T @ r)


@pytest.mark.parametrize("prior", ["curvature", "membrane"])
def test_damped_block_and_prior_gradient_equal_their_direct_forms_bit_for_bit(prior):
    """NormalBlock.damped(mu) (the undamped assembly kept, the ridge added to the diagonal pairs) gives the
    same blocks, preconditioner and ridge as a block assembled with that damping, bit for bit, and so the same
    CG solve; NormalProblem.prior_gradient (one bincount) equals its definition as a scatter-add per stencil
    place (np.add.at), bit for bit: the refinement's path is sensitive to rounding (docs/benchmarks/joint.md)."""
    from fmbrdf_mi.fit.problem.normals import NormalProblem, stencils, tangent_bases
    from fmbrdf_mi.fit.solve.normal_system import NormalBlock

    rng = np.random.default_rng(11)
    mask = np.ones((6, 8), bool)
    mask[2, 3] = mask[5, 0] = False
    st, coef = stencils(mask, prior)
    N = int(mask.sum())
    n = rng.normal(size=(N, 3))
    n[:, 2] = np.abs(n[:, 2]) + 1
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    t1, t2 = tangent_bases(n)
    pix = rng.integers(-1, N, size=(5 * N, 8))
    val = rng.normal(size=pix.shape + (2,))
    val[:, 4:][rng.random((5 * N, 4)) < 0.5] = 0.0                  # unused slots, as inside samples have
    base = NormalBlock(pix, val, st, coef, t1, t2, 0.7, 0.0)
    b = rng.normal(size=(N, 2, 3))
    for mu in (0.0, 1e-3, 0.4):
        direct, damped = NormalBlock(pix, val, st, coef, t1, t2, 0.7, mu), base.damped(mu)
        for a in ("B", "pre", "ridge"):
            assert np.array_equal(getattr(direct, a), getattr(damped, a)), (mu, a)
        assert np.array_equal(direct.solve(b), damped.solve(b))
    assert not np.array_equal(base.damped(0.4).B, base.B)           # the damping is not lost or shared
    jp = NormalProblem.__new__(NormalProblem)                       # only what prior_gradient reads
    jp.stencils, jp.coef, jp.w_prior = st, np.array(coef), 0.37
    gn0 = rng.normal(size=(N, 2))
    ref = gn0.copy()
    d = jp.w_prior * sum(c * n[st[:, s]] for s, c in enumerate(coef))
    for s, c in enumerate(coef):
        k = st[:, s]
        np.add.at(ref, k, c * np.stack([np.sum(t1[k] * d, 1), np.sum(t2[k] * d, 1)], 1))
    assert np.array_equal(jp.prior_gradient(gn0.copy(), (t1, t2), n), ref)


def test_round_time_left_extrapolates_the_decreases_to_the_stopping_rule():
    """Decreases halving from 2: 1, 0.5, ..., 0.0078 is the 8th below 0.01, the 9th the second in a row, so 9
    more iterations; capped by the iterations left; unknown before three decreases or when they grow."""
    from fmbrdf_mi.fit.api.normal_joint import round_time_left

    assert round_time_left([8.0, 4.0, 2.0], 2.0, 50) == 18.0
    assert round_time_left([8.0, 4.0, 2.0], 2.0, 5) == 10.0
    assert round_time_left([1.0, 0.1, 0.005], 1.0, 50) == 1.0
    assert round_time_left([4.0, 2.0], 1.0, 50) is None
    assert round_time_left([1.0, 2.0, 3.0], 1.0, 50) is None


def test_curvature_prior_is_zero_on_a_linear_normal_field():
    """Second differences vanish where the normal changes linearly across the image (a cylinder-like
    slope field before normalisation); first differences do not."""
    from fmbrdf_mi.fit.problem.normals import stencils

    mask = np.ones((5, 6), bool)
    y, x = np.mgrid[0:5, 0:6]
    n = np.stack([0.05 * x, -0.03 * y, np.ones_like(x, float)], -1)[mask]
    for prior, zero in (("curvature", True), ("membrane", False)):
        st, coef = stencils(mask, prior)
        d = sum(c * n[st[:, s]] for s, c in enumerate(coef))
        assert (np.abs(d).max() < 1e-12) == zero
    with pytest.raises(Exception, match="prior: expected one of"):
        stencils(mask, "tv")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A 16 x 16 super-pixel mesh object (137 refined pixels), 3 lights, raw 16-bit mosaics, authors' layout."""
    from fmbrdf_mi.synthetic.mesh_object import write_authors_object

    root = tmp_path_factory.mktemp("tiny") / "blob"
    truth = write_authors_object(root, TRUE, LIGHTS, res=16, fov=12.0, powers=POWERS, seed=3)
    return root, truth


def _observations(tiny):
    from fmbrdf_mi.fit.inputs.authors import read_object

    root, truth = tiny
    specs, _ = read_object(root, conversion_gain=truth["camera"]["conversion_gain"], read_noise=2.5)
    return [s.input for s in specs], truth["irradiance_dn"] * max(POWERS)


def _start(ks):
    return {"eta": 1.35, "alpha": 0.3, "beta": 1.2, "kappa": 5.0, "k_s": 0.9 * ks, "r_k": 0.6}


def test_normal_jacobian_matches_brute_force(tiny):
    """The chain rule of `linearise` (per-sample finite differences, then bilinear weights onto the 4 corner
    pixels) against moving one pixel's normal in the map and recomputing every residual: an interior pixel,
    whose normal enters its own and its 8 neighbours' samples, and one on the border of the refined region
    (corners outside it replaced by itself).  Both are central differences of float32 renders: the model's
    samples are ~1e4 DN with sd ~60 DN, so residual rounding is ~1e-5 and h = 1e-3 gives ~1e-2 absolute
    noise on derivatives of size ~100: 1e-3 relative to the largest entry is 10x that."""
    from fmbrdf_mi.fit.problem.normals import NormalProblem
    from fmbrdf_mi.fit.inputs.normal_maps import photometric_stereo
    from fmbrdf_mi.fit.evaluate.models import get_model
    from fmbrdf_mi.fit.evaluate.parameters import Parameters
    from fmbrdf_mi.fit.inputs.observations import erode

    obs, ks = _observations(tiny)
    m = erode(obs[0].mask, 1)
    mdl = get_model("fmbrdf")
    jp = NormalProblem(obs, m, Parameters(mdl), 0.3)
    st = jp.state(*jp.params.split(_start(ks)))
    nmap = photometric_stereo(obs).reshape(-1, 3)
    r, _, (pix, val), (t1, t2), _ = jp.linearise(st, nmap)
    nb = jp.cpix
    interior = next(i for i in range(jp.n) if len(set(nb[i].ravel())) == 9)       # its 3 x 3 neighbourhood
    border = next(i for i in range(jp.n) if 1 < len(set(nb[i].ravel())) < 9)
    for q in (interior, border):
        for a, t in enumerate((t1[q], t2[q])):
            cols = []
            for d in (1e-3, -1e-3):
                nm = nmap.copy()
                v = nm[jp.idx[q]] + d * t
                nm[jp.idx[q]] = v / np.linalg.norm(v)
                cols.append(jp.obj.residuals(jp.parts_at(st, nm), st))
            brute = (cols[0] - cols[1]) / 2e-3
            ours = np.sum(np.where(pix == q, val[:, :, a], 0.0), axis=1)
            assert np.abs(brute).max() > 1.0
            np.testing.assert_allclose(ours, brute, atol=1e-3 * np.abs(brute).max())


def test_border_ring_model_fits_the_ray_cast_data(tiny):
    """At the true material and the ray-cast normal map, the refinement's model fits the raw samples of the
    refined region's border ring (pixels with a neighbour outside it) nearly as well as inside: a sample
    corner outside the region is extrapolated linearly from the inside.  A constant extrapolation (the
    pixel's own normal) leaves a model error in the ring, where the normal turns fast towards the
    silhouette, that biases the material (tools/bench_normal_refine.py --seeds, docs/benchmarks/joint.md)."""
    from fmbrdf_mi.fit.problem.normals import NormalProblem
    from fmbrdf_mi.fit.evaluate.models import get_model
    from fmbrdf_mi.fit.evaluate.parameters import Parameters
    from fmbrdf_mi.fit.inputs.observations import erode

    obs, ks = _observations(tiny)
    m = erode(obs[0].mask, 1)
    mdl = get_model("fmbrdf")
    jp = NormalProblem(obs, m, Parameters(mdl), 0.3)
    st = jp.state(*jp.params.split(dict(TRUE, k_s=TRUE["k_s"] * ks)))
    parts = jp.parts_at(st, obs[0].normals.reshape(-1, 3))
    jp.obj.refresh(parts, st)                               # variances from the true model
    r2 = jp.obj.residuals(parts, st).reshape(jp.K, jp.n, 4) ** 2
    pad = np.pad(m, 1)
    inner = np.all([pad[1 + dy:pad.shape[0] - 1 + dy, 1 + dx:pad.shape[1] - 1 + dx]
                    for dy in (-1, 0, 1) for dx in (-1, 0, 1)], axis=0).ravel()[jp.idx]
    ring, inside = r2[:, ~inner].mean(), r2[:, inner].mean()
    assert (~inner).sum() > 20 and inner.sum() > 20
    assert inside < 1.6 and ring < 3.5 and r2.mean() < 2.2, (ring, inside, r2.mean())


def test_joint_lowers_the_energy_monotonically_to_a_minimum_near_the_truth(tiny):
    """From photometric stereo and a wrong material: every accepted step lowers the joint energy (variances
    held, refreshes=0); the energy reported is that of an independently built problem at the result; the
    result is a minimum in every pixel's normal (moving one normal by 5e-3 rad either way along either
    tangent raises that energy: at the start, some of these moves lower it); the normals end much closer to
    the ray-cast ones and every material parameter closer to the truth than it started."""
    from fmbrdf_mi.fit.api.normal_joint import refine_joint
    from fmbrdf_mi.fit.evaluate.models import get_model
    from fmbrdf_mi.fit.evaluate.parameters import Parameters
    from fmbrdf_mi.fit.inputs.normal_maps import angular_error_deg, photometric_stereo
    from fmbrdf_mi.fit.problem.normals import NormalProblem, tangent_bases

    obs, ks = _observations(tiny)
    gt = obs[0].normals.copy()
    n0 = photometric_stereo(obs)
    start = _start(ks)
    # lam_material=None: no second run with a weakened prior, so that params and normals are one state
    res = refine_joint(obs, n0, start, lam=0.3, refreshes=0, max_iter=20, lam_material=None)
    e = [h["energy"] for h in res.history]
    assert res.converged and len(e) >= 3 and all(b < a for a, b in zip(e, e[1:])), e
    mdl = get_model("fmbrdf")
    jp = NormalProblem(obs, res.mask, Parameters(mdl), 0.3)
    st = jp.state(*jp.params.split(res.params))
    ed, ep, _ = jp.energy(st, res.normals.reshape(-1, 3))
    assert abs(ed + ep - res.loss) < 1e-6 * res.loss     # the same energy, rebuilt

    def rises(nmap, d=5e-3):
        """The energy's change when one pixel's normal moves by +-d along each tangent, for 12 pixels."""
        nm = nmap.reshape(-1, 3)
        e0 = sum(jp.energy(st, nm)[:2])
        out = []
        for q in np.linspace(0, jp.n - 1, 12).astype(int):
            i = jp.idx[q]
            t1, t2 = tangent_bases(nm[i:i + 1] / np.linalg.norm(nm[i]))
            for t in (t1[0], t2[0]):
                for s in (d, -d):
                    moved = nm.copy()
                    moved[i] = (nm[i] + s * t) / np.linalg.norm(nm[i] + s * t)
                    out.append(sum(jp.energy(st, moved)[:2]) - e0)
        return np.array(out)

    assert np.all(rises(res.normals) > 0)
    assert np.sum(rises(n0) < 0) >= 4                   # the check can fail: the start is not a minimum
    e0, e1 = angular_error_deg(n0, gt, res.mask), angular_error_deg(res.normals, gt, res.mask)
    assert e1.mean() < 0.4 * e0.mean(), (e0.mean(), e1.mean())
    true = dict(TRUE, k_s=TRUE["k_s"] * ks)
    for k, v in res.params.items():
        assert abs(v - true[k]) < abs(start[k] - true[k]), (k, v, true[k], start[k])


def test_refine_normals_command(tiny, tmp_path, capsys):
    """`fmbrdf-mi fit --authors DIR --refine-normals`: outputs exist, the angle to normal_GT.npy falls, the
    material has calibrated standard errors (from the run with the weakened prior); a second run without
    --force refuses and leaves the files; K < 3 (one image
    held out) and --refine-normals on one image are one-line errors with a non-zero exit and no outputs."""
    from fmbrdf_mi.cli import main

    root, truth = tiny
    g = truth["camera"]["conversion_gain"]
    ks = truth["irradiance_dn"] * max(POWERS)
    init = ",".join(f"{k}={v!r}" for k, v in _start(ks).items())
    common = ["--authors", str(root), "--conversion-gain", repr(g), "--read-noise", "2.5", "--refine-normals",
              "--init", init, "--max-iter", "20", "-q"]
    out = tmp_path / "out"
    assert main(["fit", *common, "-o", str(out)]) in (0, 3)
    rep = json.loads((out / "fit.json").read_text())
    rn = rep["refine_normals"]
    for f in ("fit.json", "normals.npy", "normals.png", "normals_change.png"):
        assert (out / f).stat().st_size > 0
    n = np.load(out / "normals.npy")
    assert n.shape == (16, 16, 3) and np.all(np.isfinite(n))
    ae = rn["angular_error"]
    assert ae["after"]["mean"] < 0.85 * ae["before"]["mean"], ae
    assert set(rep["models"]["fmbrdf"]["params"]) == set(TRUE)
    assert "stdout" not in rep and capsys.readouterr().out.count("angle to the ground truth") == 1
    if rn["converged"]:
        # the material at the weakened prior, its standard errors calibrated (tools/bench_normal_refine.py --seeds)
        unc = rep["models"]["fmbrdf"]["uncertainty"]
        assert unc["calibrated"] and set(unc["std_errors"]) == set(TRUE)
        assert "uncertainty_uncalibrated" not in rep["models"]["fmbrdf"]
        assert rn["material_stage"]["lam"] == 0.03
    before = (out / "normals.npy").read_bytes()
    assert main(["fit", *common, "-o", str(out)]) != 0
    assert "exists; pass --force" in capsys.readouterr().err
    assert (out / "normals.npy").read_bytes() == before
    out2 = tmp_path / "k2"
    assert main(["fit", *common, "--holdout", "2", "-o", str(out2)]) != 0
    err = capsys.readouterr().err
    assert "needs K >= 3 images" in err and err.strip().count("\n") == 0, err
    assert not out2.exists() or not os.listdir(out2)
    img = str(root / "image" / "img_ud" / "000.png")
    assert main(["fit", img, "--light", "0,0,1", "--refine-normals", "-o", str(out2)]) != 0
    err = capsys.readouterr().err
    assert "--refine-normals: needs K >= 3 images" in err and err.strip().count("\n") == 0, err


def test_refinement_time_left_adds_the_rounds_still_to_run():
    """The whole refinement's time left: this round's, plus each later round at the finished rounds' mean
    duration (before one has finished: at this round's own projected duration)."""
    from fmbrdf_mi.fit.api.normal_joint import refinement_time_left

    assert refinement_time_left(5.0, [], 10.0, 2) == 5.0 + 2 * 15.0       # this round: 10 s done + 5 s left
    assert refinement_time_left(5.0, [20.0, 30.0], 3.0, 1) == 5.0 + 25.0   # the finished rounds' mean
    assert refinement_time_left(None, [20.0], 3.0, 2) == 40.0              # this round's left not known yet
    assert refinement_time_left(None, [], 3.0, 2) is None
    assert refinement_time_left(7.0, [20.0], 3.0, 0) == 7.0                 # the last round: its own time


def _random_rows(rng, N, m, Q=8, p=6):
    pix = rng.integers(0, N, size=(m, Q))
    val = rng.normal(size=(m, Q, 2))
    val[:, Q // 2:][rng.random((m, Q - Q // 2)) < 0.5] = 0.0        # unused slots, as inside samples have
    return pix, val, rng.normal(size=(m, p)), rng.normal(size=m)


def test_data_products_equal_all_columns_summed_at_once_holding_one_column_of_terms():
    """data_products' H_mn equals its definition as one bincount of all 2 p columns' terms at once (each sum's
    terms in the rows' order), bit for bit, while it holds one column's terms at a time: its peak allocation
    (tracemalloc) stays below 16 doubles per nonzero (row, slot) with p = 6, where all columns at once hold
    2 p products and 2 p indices each (about 30)."""
    import tracemalloc

    from fmbrdf_mi.fit.solve.normal_system import data_products

    rng = np.random.default_rng(3)
    N, m, p = 2000, 24000, 6
    pix, val, Jm, r = _random_rows(rng, N, m, p=p)
    row, slot = np.nonzero(np.any(val != 0, axis=2))
    q, v = pix[row, slot], val[row, slot]
    terms = (v[:, :, None] * Jm[row][:, None, :]).reshape(len(q), 2 * p)
    flat = (q[:, None] * 2 * p + np.arange(2 * p)).ravel()
    ref = np.bincount(flat, weights=terms.ravel(), minlength=N * 2 * p).reshape(N, 2, p).transpose(2, 0, 1)
    del terms, flat
    tracemalloc.start()
    try:
        Hmm, Hmn, gm, gn = data_products(pix, val, Jm, r, N)
        cur, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert np.array_equal(Hmn, ref)
    assert (peak - cur) / 8 / len(q) < 16, (peak - cur) / 8 / len(q)


def test_normal_block_keeps_its_sparsity_pattern_only_in_the_callers_cache():
    """A NormalBlock built without a cache leaves nothing behind once it is gone (tracemalloc: under 5 % of its
    peak), so a refinement's memory is released when it returns; with a cache dict the next block of the same
    pixels reuses the pattern kept there and equals a block built afresh, bit for bit."""
    import gc
    import tracemalloc

    from fmbrdf_mi.fit.problem.normals import stencils, tangent_bases
    from fmbrdf_mi.fit.solve.normal_system import NormalBlock

    rng = np.random.default_rng(5)
    mask = np.ones((40, 50), bool)
    st, coef = stencils(mask, "curvature")
    N = int(mask.sum())
    n = rng.normal(size=(N, 3))
    n[:, 2] = np.abs(n[:, 2]) + 1
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    t1, t2 = tangent_bases(n)
    pix, val, _, _ = _random_rows(rng, N, 12 * N, Q=4)
    tracemalloc.start()
    try:
        blk = NormalBlock(pix, val, st, coef, t1, t2, 0.7, 0.1)
        B = blk.B.copy()
        del blk
        gc.collect()
        cur, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert cur < 0.05 * peak + B.nbytes, (cur, peak)
    cache = {}
    first = NormalBlock(pix, val, st, coef, t1, t2, 0.7, 0.1, cache=cache)
    kept = cache["value"]
    second = NormalBlock(pix, 2 * val, st, coef, t1, t2, 0.7, 0.1, cache=cache)
    assert cache["value"] is kept and np.array_equal(first.B, B)
    assert np.array_equal(second.B, NormalBlock(pix, 2 * val, st, coef, t1, t2, 0.7, 0.1).B)


def _bilinear_rows(H, W, K=3):
    """The refinement's row pattern on a full H x W mask: each pixel's 4 samples read a 2 x 2 window of the
    map (4 slots) and 4 unused slots (the pixel itself, weight 0), rows (image, pixel, sample)."""
    N = H * W
    ys, xs = np.divmod(np.arange(N), W)
    lists = []
    for dy, dx in ((0, 0), (0, -1), (-1, 0), (-1, -1)):
        y0, x0 = np.clip(ys + dy, 0, H - 2), np.clip(xs + dx, 0, W - 2)
        c = np.stack([y0 * W + x0, y0 * W + x0 + 1, (y0 + 1) * W + x0, (y0 + 1) * W + x0 + 1], 1)
        lists.append(np.concatenate([c, np.repeat(np.arange(N)[:, None], 4, 1)], 1))
    return np.tile(np.stack(lists, 1).reshape(-1, 8), (K, 1))


def _random_block(H, W, seed, scale):
    """A full H x W mask's curvature stencils, random unit normals' tangent bases, the bilinear row pattern
    and random Jacobian values (``scale``) on its four used slots: NormalBlock's inputs."""
    from fmbrdf_mi.fit.problem.normals import stencils, tangent_bases

    st, coef = stencils(np.ones((H, W), bool), "curvature")
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(H * W, 3))
    n[:, 2] = np.abs(n[:, 2]) + 1
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    t1, t2 = tangent_bases(n)
    pix = _bilinear_rows(H, W)
    val = scale * rng.normal(size=pix.shape + (2,))
    val[:, 4:] = 0.0
    return (pix, val, st, coef, t1, t2), rng


def test_normal_block_assembles_a_chunk_of_lists_at_a_time():
    """The data blocks of H_nn formed a few pixel lists at a time equal those formed all at once, bit for bit,
    and re-assembling with the sparsity pattern cached then peaks (tracemalloc) at under three quarters of
    the memory of all lists' 16 x 16 products at once."""
    import tracemalloc

    from fmbrdf_mi.fit.solve import normal_system as NS

    (pix, val, st, coef, t1, t2), _ = _random_block(40, 40, 9, 1.0)
    cache = {}
    NS.NormalBlock(pix, val, st, coef, t1, t2, 0.7, 0.1, cache=cache)
    out, peak = {}, {}
    chunk = NS.CHUNK
    try:
        for c in (cache["value"]["G"], 256):
            NS.CHUNK = c
            tracemalloc.start()
            try:
                out[c] = NS.NormalBlock(pix, val, st, coef, t1, t2, 0.7, 0.1, cache=cache)
                peak[c] = tracemalloc.get_traced_memory()[1]
            finally:
                tracemalloc.stop()
    finally:
        NS.CHUNK = chunk
    whole, parts = out.values()
    for a in ("B", "B0", "pre", "ridge"):
        assert np.array_equal(getattr(whole, a), getattr(parts, a)), a
    assert peak[256] < 0.75 * peak[cache["value"]["G"]], peak


def test_block_solve_is_the_textbook_preconditioned_cg_bit_for_bit():
    """NormalBlock.solve (one gather array and in-place updates reused over its iterations) gives the textbook
    preconditioned conjugate gradients' iterate, written here with a new array at every step, bit for bit."""
    from fmbrdf_mi.fit.solve.normal_system import NormalBlock

    H, W = 9, 11
    (pix, val, st, coef, t1, t2), rng = _random_block(H, W, 2, 0.1)
    blk = NormalBlock(pix, val, st, coef, t1, t2, 0.3, 1e-3)
    b = rng.normal(size=(H * W, 2, 3))
    x, r = np.zeros_like(b), b.copy()
    z = blk.precondition(r)
    p = z.copy()
    rz = np.einsum("nar,nar->r", r, z)
    bn = np.sqrt(np.einsum("nar,nar->r", b, b))
    for it in range(5000):
        Ap = blk.apply(p)
        pAp = np.einsum("nar,nar->r", p, Ap)
        alpha = np.where(pAp > 0, rz / np.where(pAp > 0, pAp, 1.0), 0.0)
        x = x + alpha * p
        r = r - alpha * Ap
        if np.all(np.sqrt(np.einsum("nar,nar->r", r, r)) <= 1e-10 * bn):
            break
        z = blk.precondition(r)
        rz_new = np.einsum("nar,nar->r", r, z)
        beta = np.where(rz > 0, rz_new / np.where(rz > 0, rz, 1.0), 0.0)
        p = z + beta * p
        rz = rz_new
    assert it > 5 and np.array_equal(blk.solve(b), x)
