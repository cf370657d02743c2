"""Tetrahedral (simplex) interpolation of a multi-channel 3-D table in Dr.Jit.

The unit cube of each cell is split into the six tetrahedra x_a >= x_b >= x_c;
a lookup reads 4 texels instead of trilinear interpolation's 8, with the same
O(h^2) error, and is exact for affine functions.  The body tables are read at
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


class TetraTable:
    """``values``: flat Dr.Jit array of a (n0, n1, n2, C) C-order table whose
    nodes sit at coordinates i / (n - 1) in [0, 1] along each axis."""

    def __init__(self, values, shape):
        self.values = values
        self.shape = tuple(int(s) for s in shape)
        n0, n1, n2, c = self.shape
        self.strides = (n1 * n2 * c, n2 * c, c)

    def scalar_copy(self):
        """The same table for scalar lookups (Python floats; NumPy storage)."""
        return TetraTable(np.asarray(dr.detach(self.values), dtype=np.float64), self.shape)

    def eval(self, u0, u1, u2):
        """Interpolated channels (a list of C arrays) at coordinates in [0, 1] (clamped)."""
        Float = type(u0)
        weights, corners = self.corners(u0, u1, u2)
        out = []
        for ch in range(self.shape[3]):
            acc = 0.0
            for w, idx in zip(weights, corners):
                acc = acc + w * gather(Float, self.values, idx + ch)
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
        a, b, c = frac
        s0, s1, s2 = (UInt(s) for s in self.strides)
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
    reads are what costs (README, Speed of eval): one 16-byte texel per corner
    sits in one cache line and takes two 64-bit gathers, against one 32-bit
    gather per channel for the float table.  The bits carry no AD graph: use
    it only where no parameter of the table has gradients enabled.
    """

    def __init__(self, table, words):
        Float = type(table.values)
        UInt = dr.uint32_array_t(Float)
        UInt64 = dr.uint64_array_t(Float)
        n0, n1, n2, c = table.shape
        layout = [[(int(ch), int(b)) for ch, b in w] for w in words]
        if len(layout) != 2 or sorted(ch for w in layout for ch, _ in w) != list(range(c)) \
                or any(sum(b for _, b in w) > 64 for w in layout) or any(not 1 <= b <= 24 for w in layout for _, b in w):
            raise ValueError("PackedTetraTable: words must place every channel once, 1-24 bits each, "
                             "at most 64 bits per word")
        vals = dr.detach(table.values)
        n = n0 * n1 * n2
        texel = dr.arange(UInt, n)
        self.lo, self.step = [None] * c, [None] * c
        packed = []
        for w in layout:
            word, shift = UInt64(0), 0
            for ch, b in w:
                x = dr.gather(Float, vals, texel * c + ch)
                lo, hi = dr.min(x), dr.max(x)
                top = float(2 ** b - 1)
                step = dr.maximum(hi - lo, 1e-30) * (1.0 / top)
                q = UInt(dr.clip(dr.round((x - lo) / step), 0.0, top))
                word = word | (UInt64(q) << shift)
                self.lo[ch], self.step[ch] = lo, step
                shift += b
            packed.append(word)
        k = dr.arange(UInt, 2 * n)
        values = dr.select(k % 2 == 0, dr.gather(UInt64, packed[0], k // 2), dr.gather(UInt64, packed[1], k // 2))
        dr.make_opaque(values, *self.lo, *self.step)
        TetraTable.__init__(self, values, (n0, n1, n2, 2))
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
