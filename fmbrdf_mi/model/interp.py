"""Tetrahedral (simplex) interpolation of a multi-channel 3-D table in Dr.Jit.

The unit cube of each cell is split into the six tetrahedra x_a >= x_b >= x_c
(around the diagonal (1, 1, 1)) or their mirror images around another long
diagonal, one choice per table (:func:`orientation`); a lookup reads 4 texels
instead of trilinear interpolation's 8, with the same O(h^2) error, and is
exact for affine functions.  The body tables are read at
random in eval, where the number of gathered texels sets the cost, so this
halves it.  Gathers from a differentiable table carry gradients to the table.
"""
import drjit as dr
import numpy as np


def gather(Float, values, index):
    """``dr.gather``; in scalar variants (``Float is float``) ``values`` is a
    NumPy array and this is plain indexing."""
    if Float is float:
        return float(values[int(index)])
    return dr.gather(Float, values, index)


#: (s1, s2) of the four triangulations' diagonals (1, s1, s2), by pattern.
DIAGONALS = ((1, 1), (-1, 1), (1, -1), (-1, -1))
#: Another triangulation than pattern 0 is picked only if its estimated sum
#: of squared errors is below this fraction of pattern 0's (:func:`orientation`).
MARGIN = 0.85


def orientation(table, channel=0, costs=False):
    """Which of four triangulations of the cells interpolates ``channel`` of a
    :class:`TetraTable` best: a pattern 0-3 (a width-1 UInt32, opaque), the
    same for every cell so that the interpolant stays continuous.  ``costs``:
    also return each pattern's estimated sum of squared errors over pattern
    0's (tools/check_accuracy.py --table-only --triangulations prints them beside the errors
    measured).

    Kuhn's triangulation splits a cell into the six tetrahedra around one of
    its four long diagonals (1, s1, s2), s1, s2 = +-1 (pattern bit 0 flips
    axis 1, bit 1 axis 2).  For a quadratic with Hessian H (index units) the
    linear interpolant on a simplex with barycentric coordinates lambda errs
    by 1/2 sum_{i<j} lambda_i lambda_j e_ij^T H e_ij over its edges e_ij,
    which averages over a cell to e = (tr H + s1 H01 + s2 H02 + s1 s2 H12) / 12:
    the error is least where the tetrahedra's edges run along the directions
    in which the table curves least.  A function peaked along
    theta_L - theta_V wants another diagonal than one peaked along
    theta_L + theta_V (the body table: backscatter, forward scattering at
    small alpha, where the flipped triangulations halve the error).  The
    pattern with the smallest sum of e^2 over the cells is picked, pattern 0
    unless another's is below MARGIN times its (the estimate is rough: where
    two patterns' estimates differ by less than about 15 %, their errors
    measured by tools/check_accuracy.py --table-only --triangulations come in either order).
    Sum of e^2 = X0 + 2 (s1 X1 + s2 X2 + s1 s2 X3) with
    X0 = sum(tr^2 + H01^2 + H02^2 + H12^2), X1 = sum(tr H01 + H02 H12),
    X2 = sum(tr H02 + H01 H12), X3 = sum(tr H12 + H01 H02).  H from the
    table's own values: the mixed terms from each cell's eight corners, the
    diagonal ones from second differences along its three base edges (one
    more node each).

    Choosing per cell would be more accurate but not continuous: two cells
    sharing a face must split it along the same diagonal, which forces s1 s2
    to be the same along axis 0, s1 along axis 2 and s2 along axis 1, and the
    body table wants different diagonals at different phi.  A table-wide
    choice keeps the lookup continuous in its coordinates; between two
    materials on either side of a change of pattern it jumps by the
    difference of the two interpolants, within the interpolation error.
    """
    values, offset = table.channel(channel)
    values = dr.detach(values)
    dr.eval(values)  # gathered 11 times a cell: not to be recomputed in each
    Float = type(values)
    UInt = dr.uint32_array_t(Float)
    n0, n1, n2 = table.shape[:3]
    t0, t1, t2 = table.strides
    m1, m2 = n1 - 1, n2 - 1
    cell = dr.arange(UInt, (n0 - 1) * m1 * m2)
    i2, i1, i0 = cell % m2, (cell // m2) % m1, cell // (m1 * m2)
    base = i0 * t0 + i1 * t1 + i2 * t2 + offset
    at = lambda off: dr.gather(Float, values, base + off)
    k = {(a, b, d): at(a * t0 + b * t1 + d * t2) for a in (0, 1) for b in (0, 1) for d in (0, 1)}
    h01 = 0.5 * sum(k[1, 1, d] - k[1, 0, d] - k[0, 1, d] + k[0, 0, d] for d in (0, 1))
    h02 = 0.5 * sum(k[1, b, 1] - k[1, b, 0] - k[0, b, 1] + k[0, b, 0] for b in (0, 1))
    h12 = 0.5 * sum(k[a, 1, 1] - k[a, 1, 0] - k[a, 0, 1] + k[a, 0, 0] for a in (0, 1))
    tr = 0.0
    for i, n, stride, f1 in ((i0, n0, t0, k[1, 0, 0]), (i1, n1, t1, k[0, 1, 0]), (i2, n2, t2, k[0, 0, 1])):
        # the second difference at the base node, or at the next one on the first cell
        before = at(UInt(0) - stride * dr.minimum(i, 1))
        after = at(stride * dr.minimum(2, n - 1 - i))
        tr += dr.select(i > 0, before - 2.0 * k[0, 0, 0] + f1, k[0, 0, 0] - 2.0 * f1 + after)
    x = [tr * h01 + h02 * h12, tr * h02 + h01 * h12, tr * h12 + h01 * h02, tr * tr + h01 * h01 + h02 * h02 + h12 * h12]
    dr.eval(*x)  # one kernel; then the sums
    x1, x2, x3, x0 = (dr.sum(v) for v in x)
    cost = [x0 + 2.0 * (s1 * x1 + s2 * x2 + s1 * s2 * x3) for s1, s2 in DIAGONALS]
    best, pattern = cost[0] * MARGIN, UInt(0)
    for p in (1, 2, 3):
        better = cost[p] < best
        best, pattern = dr.select(better, cost[p], best), dr.select(better, UInt(p), pattern)
    dr.make_opaque(pattern)
    return (pattern, [c / dr.maximum(cost[0], 1e-30) for c in cost]) if costs else pattern


class TetraTable:
    """A (n0, n1, n2, C) table whose nodes sit at coordinates i / (n - 1) in
    [0, 1] along each axis.  ``values``: one flat Dr.Jit array in C order (a
    texel's channels side by side), or a list of C flat arrays (``planar``:
    one per channel, what :class:`PackedTetraTable` is built from fastest).
    ``orient``: the cells' triangulation (:func:`orientation`), chosen from
    channel 0 when not given."""

    def __init__(self, values, shape, orient=None):
        self.values = values
        self.shape = tuple(int(s) for s in shape)
        n0, n1, n2, c = self.shape
        self.planar = isinstance(values, (list, tuple))
        if self.planar and len(values) != c:
            raise ValueError("TetraTable: a planar table needs one array per channel")
        self.strides = (n1 * n2, n2, 1) if self.planar else (n1 * n2 * c, n2 * c, c)
        self.orient = orientation(self) if orient is None else orient

    def channel(self, ch):
        """(array, offset): channel ``ch`` of the texel at flat offset i is array[i + offset]."""
        return (self.values[ch], 0) if self.planar else (self.values, ch)

    def scalar_copy(self):
        """The same table for scalar lookups (Python floats; NumPy storage)."""
        copy = lambda x: np.asarray(dr.detach(x), dtype=np.float64)
        values = [copy(x) for x in self.values] if self.planar else copy(self.values)
        return TetraTable(values, self.shape, int(self.orient[0]))

    def eval(self, u0, u1, u2):
        """Interpolated channels (a list of C arrays) at coordinates in [0, 1] (clamped)."""
        Float = type(u0)
        weights, corners = self.corners(u0, u1, u2)
        out = []
        for ch in range(self.shape[3]):
            acc = 0.0
            values, offset = self.channel(ch)
            for w, idx in zip(weights, corners):
                acc = acc + w * gather(Float, values, idx + offset)
            out.append(acc)
        return out

    def corners(self, u0, u1, u2):
        """The tetrahedron around (u0, u1, u2): 4 weights and 4 flat texel offsets."""
        Float = type(u0)
        UInt = dr.uint32_array_t(Float)
        base = UInt(0)
        frac = []
        for u, n, stride in zip((u0, u1, u2), self.shape[:3], self.strides):
            f = dr.clip(u, 0.0, 1.0) * (n - 1)
            i = dr.minimum(UInt(f), n - 2)
            base += i * stride
            frac.append(f - Float(i))
        flip1, flip2 = (self.orient & 1) != 0, (self.orient & 2) != 0
        a, b, c = frac
        s0, s1, s2 = (UInt(s) for s in self.strides)
        # the six tetrahedra around the diagonal (1, s1, s2): mirror the flipped axes
        b, c = dr.select(flip1, 1.0 - b, b), dr.select(flip2, 1.0 - c, c)
        base += dr.select(flip1, s1, 0) + dr.select(flip2, s2, 0)
        s1, s2 = dr.select(flip1, UInt(0) - s1, s1), dr.select(flip2, UInt(0) - s2, s2)
        # order the fractions: largest first; step along its axis, then the next
        ab, bc, ac = a >= b, b >= c, a >= c
        first = dr.select(ab & ac, s0, dr.select(bc, s1, s2))
        last = dr.select(ab, dr.select(bc, s2, s1), dr.select(ac, s2, s0))
        f1 = dr.maximum(dr.maximum(a, b), c)
        f3 = dr.minimum(dr.minimum(a, b), c)
        f2 = a + b + c - f1 - f3
        weights = (1.0 - f1, f1 - f2, f2 - f3, f3)
        corners = (base, base + first, base + (s0 + s1 + s2) - last, base + s0 + s1 + s2)
        return weights, corners


class PackedTetraTable(TetraTable):
    """The same interpolation from 16 bytes per texel: every channel in fixed
    point, ``bits[c]`` bits each, packed into two 64-bit words per texel.

    ``words``: for each of the two 64-bit words, the channels it holds, from
    the low bits up (at most 64 bits per word).  Channel c is stored as
    q = round((x - lo_c) / step_c), step_c = (hi_c - lo_c) / (2^b - 1) over its
    own range [lo_c, hi_c] in this table, so it is within step_c / 2 of the
    float32 value; interpolation is exact on q (a convex combination), and
    lo_c + step_c sum_k w_k q_k restores the value.  eval's random-access
    reads are what costs (docs/benchmarks/speed.md): one 16-byte texel per corner
    sits in one cache line and takes two 64-bit gathers, against one 32-bit
    gather per channel for the float table.  The bits carry no AD graph: use
    it only where no parameter of the table has gradients enabled.  Built
    fastest from a ``planar`` table (each channel read as one stream).
    """

    def __init__(self, table, words):
        Float = type(table.channel(0)[0])
        UInt = dr.uint32_array_t(Float)
        UInt64 = dr.uint64_array_t(Float)
        n0, n1, n2, c = table.shape
        layout = [[(int(ch), int(b)) for ch, b in w] for w in words]
        if len(layout) != 2 or sorted(ch for w in layout for ch, _ in w) != list(range(c)) \
                or any(sum(b for _, b in w) > 64 for w in layout) or any(not 1 <= b <= 24 for w in layout for _, b in w):
            raise ValueError("PackedTetraTable: words must place every channel once, 1-24 bits each, "
                             "at most 64 bits per word")
        n = n0 * n1 * n2
        texel = dr.arange(UInt, n)
        chans = [table.channel(ch) for ch in range(c)]
        chans = [dr.detach(x) if table.planar else dr.gather(Float, dr.detach(x), texel * c + off) for x, off in chans]
        ranges = [(dr.min(x), dr.max(x)) for x in chans]
        tops = {ch: float(2 ** b - 1) for w in layout for ch, b in w}
        self.lo = [lo for lo, _ in ranges]
        self.step = [dr.maximum(hi - lo, 1e-30) * (1.0 / tops[ch]) for ch, (lo, hi) in enumerate(ranges)]
        dr.make_opaque(*self.lo, *self.step)
        packed = []
        for w in layout:
            word, shift = UInt64(0), 0
            for ch, b in w:
                q = UInt(dr.clip(dr.round((chans[ch] - self.lo[ch]) / self.step[ch]), 0.0, tops[ch]))
                word = word | (UInt64(q) << shift)
                shift += b
            packed.append(word)
        k = dr.arange(UInt, 2 * n)
        values = dr.select(k % 2 == 0, dr.gather(UInt64, packed[0], k // 2), dr.gather(UInt64, packed[1], k // 2))
        dr.make_opaque(values)
        TetraTable.__init__(self, values, (n0, n1, n2, 2), table.orient)
        self.layout, self.channels = layout, c

    def scalar_copy(self):
        raise NotImplementedError("packed tables are for the JIT variants")

    def eval(self, u0, u1, u2):
        Float = type(u0)
        UInt = dr.uint32_array_t(Float)
        UInt64 = dr.uint64_array_t(Float)
        weights, corners = self.corners(u0, u1, u2)
        acc = [0.0] * self.channels
        for w, idx in zip(weights, corners):
            for k, fields in enumerate(self.layout):
                word, shift = dr.gather(UInt64, self.values, idx + k), 0
                for ch, b in fields:
                    q = UInt((word >> shift) & ((1 << b) - 1)) if shift + b < 64 else UInt(word >> shift)
                    acc[ch] = dr.fma(w, Float(q), acc[ch])
                    shift += b
        return [dr.fma(self.step[ch], a, self.lo[ch]) for ch, a in enumerate(acc)]


class LineTable:
    """Linear interpolation of a multi-channel 1-D table: ``values`` is a flat
    array of a (n, C) C-order table whose nodes sit at i / (n - 1) in [0, 1].
    Small enough to stay in the L1 cache: eval reads it at random for free
    compared with the 3-D tables."""

    def __init__(self, values, shape):
        self.values = values
        self.shape = tuple(int(s) for s in shape)

    def scalar_copy(self):
        return LineTable(np.asarray(dr.detach(self.values), dtype=np.float64), self.shape)

    def eval(self, u):
        """Interpolated channels (a list of C arrays) at ``u`` in [0, 1] (clamped)."""
        Float = type(u)
        UInt = dr.uint32_array_t(Float)  # int for Python floats (scalar variants)
        n, c = self.shape
        f = dr.clip(u, 0.0, 1.0) * (n - 1)
        i = dr.minimum(UInt(f), n - 2)
        t = f - Float(i)
        out = []
        for ch in range(c):
            v0 = gather(Float, self.values, i * c + ch)
            v1 = gather(Float, self.values, (i + 1) * c + ch)
            out.append(dr.fma(t, v1 - v0, v0))
        return out

    def paired(self):
        """The same two-channel table read with one 64-bit gather per node
        (JIT variants; no AD graph)."""
        return PairedLineTable(self)


class PairedLineTable(LineTable):
    """A two-channel :class:`LineTable` whose nodes' channels share a 64-bit
    word: each of the two nodes around ``u`` is one gather instead of two."""

    def __init__(self, table):
        Float = type(table.values)
        UInt = dr.uint32_array_t(Float)
        UInt64 = dr.uint64_array_t(Float)
        n, c = table.shape
        if c != 2:
            raise ValueError("PairedLineTable: the table must have two channels")
        vals = dr.detach(table.values)
        k = dr.arange(UInt, n)
        bits = lambda ch: UInt64(dr.reinterpret_array(UInt, dr.gather(Float, vals, 2 * k + ch)))
        values = bits(0) | (bits(1) << 32)
        dr.make_opaque(values)
        LineTable.__init__(self, values, (n, 1))
        self.channels = c

    def scalar_copy(self):
        raise NotImplementedError("paired tables are for the JIT variants")

    def eval(self, u):
        Float = type(u)
        UInt = dr.uint32_array_t(Float)
        UInt64 = dr.uint64_array_t(Float)
        n = self.shape[0]
        f = dr.clip(u, 0.0, 1.0) * (n - 1)
        i = dr.minimum(UInt(f), n - 2)
        t = f - Float(i)
        w0, w1 = dr.gather(UInt64, self.values, i), dr.gather(UInt64, self.values, i + 1)
        out = []
        for shift in (0, 32):
            v0 = dr.reinterpret_array(Float, UInt(w0 >> shift) if shift else UInt(w0))
            v1 = dr.reinterpret_array(Float, UInt(w1 >> shift) if shift else UInt(w1))
            out.append(dr.fma(t, v1 - v0, v0))
        return out
