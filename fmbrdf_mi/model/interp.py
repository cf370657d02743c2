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
    """The same interpolation from fewer bytes: the first ``n_float``
    channels stay float32, the others (an even number, values in [-bound,
    bound]) are stored as 16-bit fixed point, two to a 32-bit word (step
    bound / 32767: for bound 2, at most 3.1e-5 from the float32 value, a
    hundredth of the tables' interpolation error).  eval's random-access
    reads are what costs: fewer bytes keep more of the table in the caches
    and fewer words are gathered per texel.  The bits carry no AD graph: use
    it only where no parameter of the table has gradients enabled.
    """

    def __init__(self, table, n_float=0, bound=2.0):
        Float = type(table.values)
        UInt = dr.uint32_array_t(Float)
        Int = dr.int32_array_t(Float)
        n0, n1, n2, c = table.shape
        if (c - n_float) % 2:
            raise ValueError("PackedTetraTable: the packed channels must come in pairs")
        n_words = n_float + (c - n_float) // 2
        self.scale = bound / 32767.0
        vals = dr.detach(table.values)
        idx = dr.arange(UInt, n0 * n1 * n2 * n_words)
        texel, k = idx // n_words, idx % n_words
        first = dr.select(k < n_float, k, n_float + 2 * (k - n_float))
        a = dr.gather(Float, vals, texel * c + first)
        b = dr.gather(Float, vals, texel * c + dr.minimum(first + 1, c - 1))
        q = [Int(dr.round(dr.clip(x, -bound, bound) * (1.0 / self.scale))) for x in (a, b)]
        words = dr.select(k < n_float, dr.reinterpret_array(UInt, a),
                          dr.reinterpret_array(UInt, (q[0] & 0xFFFF) | (q[1] << 16)))
        dr.eval(words)
        TetraTable.__init__(self, words, (n0, n1, n2, n_words))
        self.n_float, self.channels = n_float, c

    def scalar_copy(self):
        raise NotImplementedError("packed tables are for the JIT variants")

    def eval(self, u0, u1, u2):
        Float = type(u0)
        UInt = dr.uint32_array_t(Float)
        Int = dr.int32_array_t(Float)
        weights, corners = self.corners(u0, u1, u2)
        nf = self.n_float
        out = [0.0] * self.channels
        for w, idx in zip(weights, corners):
            for k in range(self.shape[3]):
                word = dr.gather(UInt, self.values, idx + k)
                if k < nf:
                    out[k] = out[k] + w * dr.reinterpret_array(Float, word)
                    continue
                word = dr.reinterpret_array(Int, word)
                j = nf + 2 * (k - nf)
                out[j] = out[j] + w * Float((word << 16) >> 16)
                out[j + 1] = out[j + 1] + w * Float(word >> 16)
        return [o if k < nf else o * self.scale for k, o in enumerate(out)]
