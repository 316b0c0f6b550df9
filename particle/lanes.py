"""Explicit SIMD lanes for the compiled kernels: ``LANES`` float64 values as one vector.

LLVM does not vectorise the connector and tet passes by itself: their stores may alias
their gathered loads, which it cannot check. These numba intrinsics let a kernel say
what it wants: a vector is a ``UniTuple(float64, LANES)`` (LLVM ``[LANES x double]``);
each intrinsic turns its operands into an LLVM ``<LANES x double>``, applies one IEEE
operation (add, subtract, multiply, divide, square root: the same correctly rounded
operation per lane as the scalar code, no contraction into fused multiply-adds), and
turns the result back, and LLVM folds the conversions away. A kernel written lane-wise
thus computes bit for bit what its scalar loop computes.

Loads of per-item data (``item`` .. ``item + LANES - 1`` of a 1-d array or of one column
pair of an (n, 2) array) are one contiguous vector load for C-contiguous arrays and lane
by lane otherwise; the particles' coordinates are gathered by scalar loads put into lanes
(:func:`gather_rows`): on the AMD Zen 4 cores this was measured on, the AVX-512 gather
instruction was slower (the connectors' lane arithmetic on the 12k-connector liver, without
the scatter: 51 against 33 us). Four lanes (:data:`LANES`) measured faster than eight or
two there.
"""

from __future__ import annotations

from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

LANES = 4  # float64 values per vector
ALL_LANES = (1 << LANES) - 1  # the lane mask with every lane set
VECTOR = types.UniTuple(types.float64, LANES)
_DOUBLE = ir.DoubleType()
_V = ir.VectorType(_DOUBLE, LANES)
_I64 = ir.IntType(64)
_I32 = ir.IntType(32)


def _to_vector(builder, value):
    """The LLVM vector of a lane tuple."""
    v = ir.Constant(_V, ir.Undefined)
    for k in range(LANES):
        v = builder.insert_element(v, builder.extract_value(value, k), ir.Constant(_I32, k))
    return v


def _from_vector(builder, v):
    """The lane tuple of an LLVM vector."""
    t = ir.Constant(ir.ArrayType(_DOUBLE, LANES), ir.Undefined)
    for k in range(LANES):
        t = builder.insert_value(t, builder.extract_element(v, ir.Constant(_I32, k)), k)
    return t


def _is_float_array(ty, ndim) -> bool:
    return isinstance(ty, types.Array) and ty.dtype == types.float64 and ty.ndim == ndim


def _element(context, builder, aryty, ary, indices):
    """Pointer to ``ary[indices]`` (no wrap-around: the kernels' indices are >= 0)."""
    return cgutils.get_item_pointer(context, builder, aryty, ary, indices)


def _binary(op: str, doc: str):
    @intrinsic
    def fn(typingctx, a, b):
        if a != VECTOR or b != VECTOR:
            return None

        def codegen(context, builder, sig, args):
            r = getattr(builder, op)(_to_vector(builder, args[0]), _to_vector(builder, args[1]))
            return _from_vector(builder, r)
        return VECTOR(a, b), codegen
    fn.__doc__ = doc
    return fn


vadd = _binary("fadd", "Lane-wise a + b.")
vsub = _binary("fsub", "Lane-wise a - b.")
vmul = _binary("fmul", "Lane-wise a * b.")
vdiv = _binary("fdiv", "Lane-wise a / b.")


@intrinsic
def vsqrt(typingctx, a):
    """Lane-wise sqrt(a) (correctly rounded, as math.sqrt)."""
    if a != VECTOR:
        return None

    def codegen(context, builder, sig, args):
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(_V, [_V]),
                                            f"llvm.sqrt.v{LANES}f64")
        return _from_vector(builder, builder.call(fn, [_to_vector(builder, args[0])]))
    return VECTOR(a), codegen


@intrinsic
def vsplat(typingctx, value):
    """The vector with ``value`` in every lane."""
    if not isinstance(value, types.Float):
        return None

    def codegen(context, builder, sig, args):
        value = context.cast(builder, args[0], sig.args[0], types.float64)
        v = ir.Constant(_V, ir.Undefined)
        for k in range(LANES):
            v = builder.insert_element(v, value, ir.Constant(_I32, k))
        return _from_vector(builder, v)
    return VECTOR(value), codegen


def _compare(predicate: str, doc: str):
    @intrinsic
    def fn(typingctx, a, b):
        if a != VECTOR or b != VECTOR:
            return None

        def codegen(context, builder, sig, args):
            bits = builder.fcmp_ordered(predicate, _to_vector(builder, args[0]),
                                        _to_vector(builder, args[1]))
            mask = builder.bitcast(bits, ir.IntType(LANES))
            return builder.zext(mask, _I64)
        return types.int64(a, b), codegen
    fn.__doc__ = doc
    return fn


vle_mask = _compare("<=", "Bit k set where lane k of a <= b (ordered: a NaN lane clears it).")
vlt_mask = _compare("<", "Bit k set where lane k of a < b (ordered: a NaN lane clears it).")


@intrinsic
def vload(typingctx, ary, item):
    """``ary[item : item + LANES]`` of a 1-d float64 array."""
    if not (_is_float_array(ary, 1) and isinstance(item, types.Integer)):
        return None

    def codegen(context, builder, sig, args):
        aryty, (value, item) = sig.args[0], args
        item = context.cast(builder, item, sig.args[1], types.intp)
        array = context.make_array(aryty)(context, builder, value)
        if aryty.layout == "C":
            ptr = _element(context, builder, aryty, array, [item])
            return _from_vector(builder, builder.load(builder.bitcast(ptr, _V.as_pointer()),
                                                      align=8))
        v = ir.Constant(_V, ir.Undefined)
        for k in range(LANES):
            ptr = _element(context, builder, aryty, array,
                           [builder.add(item, ir.Constant(item.type, k))])
            v = builder.insert_element(v, builder.load(ptr), ir.Constant(_I32, k))
        return _from_vector(builder, v)
    return VECTOR(ary, item), codegen


@intrinsic
def vstore(typingctx, ary, item, v):
    """``ary[item : item + LANES] = v`` of a 1-d float64 array."""
    if not (_is_float_array(ary, 1) and v == VECTOR):
        return None

    def codegen(context, builder, sig, args):
        aryty, (value, item, vec) = sig.args[0], args
        item = context.cast(builder, item, sig.args[1], types.intp)
        array = context.make_array(aryty)(context, builder, value)
        vec = _to_vector(builder, vec)
        if aryty.layout == "C":
            ptr = _element(context, builder, aryty, array, [item])
            builder.store(vec, builder.bitcast(ptr, _V.as_pointer()), align=8)
        else:
            for k in range(LANES):
                ptr = _element(context, builder, aryty, array,
                               [builder.add(item, ir.Constant(item.type, k))])
                builder.store(builder.extract_element(vec, ir.Constant(_I32, k)), ptr)
        return context.get_dummy_value()
    return types.none(ary, item, v), codegen


_EVEN = [2 * k for k in range(LANES)]
_ODD = [2 * k + 1 for k in range(LANES)]
_INTERLEAVE = [(k // 2) + (LANES if k % 2 else 0) for k in range(2 * LANES)]


@intrinsic
def vload2(typingctx, ary, item):
    """(``ary[item : item + LANES, 0]``, ``ary[item : item + LANES, 1]``) of an (n, 2)
    float64 array."""
    if not _is_float_array(ary, 2):
        return None

    def codegen(context, builder, sig, args):
        aryty, (value, item) = sig.args[0], args
        item = context.cast(builder, item, sig.args[1], types.intp)
        array = context.make_array(aryty)(context, builder, value)
        zero, one = ir.Constant(item.type, 0), ir.Constant(item.type, 1)
        if aryty.layout == "C":  # 2 LANES contiguous values, deinterleaved
            ptr = _element(context, builder, aryty, array, [item, zero])
            both = builder.load(builder.bitcast(ptr, ir.VectorType(_DOUBLE, 2 * LANES)
                                                .as_pointer()), align=8)
            cols = [builder.shuffle_vector(both, both, ir.Constant(ir.VectorType(_I32, LANES),
                                                                   lanes))
                    for lanes in (_EVEN, _ODD)]
        else:
            cols = []
            for col in (zero, one):
                v = ir.Constant(_V, ir.Undefined)
                for k in range(LANES):
                    ptr = _element(context, builder, aryty, array,
                                   [builder.add(item, ir.Constant(item.type, k)), col])
                    v = builder.insert_element(v, builder.load(ptr), ir.Constant(_I32, k))
                cols.append(v)
        out = ir.Constant(context.get_value_type(sig.return_type), ir.Undefined)
        out = builder.insert_value(out, _from_vector(builder, cols[0]), 0)
        return builder.insert_value(out, _from_vector(builder, cols[1]), 1)
    return types.UniTuple(VECTOR, 2)(ary, item), codegen


@intrinsic
def vstore2(typingctx, ary, item, first, second):
    """``ary[item : item + LANES, 0] = first``, ``ary[item : item + LANES, 1] = second`` of
    an (n, 2) float64 array."""
    if not (_is_float_array(ary, 2) and first == VECTOR and second == VECTOR):
        return None

    def codegen(context, builder, sig, args):
        aryty, (value, item, a, b) = sig.args[0], args
        item = context.cast(builder, item, sig.args[1], types.intp)
        array = context.make_array(aryty)(context, builder, value)
        a, b = _to_vector(builder, a), _to_vector(builder, b)
        zero, one = ir.Constant(item.type, 0), ir.Constant(item.type, 1)
        if aryty.layout == "C":
            both = builder.shuffle_vector(a, b, ir.Constant(ir.VectorType(_I32, 2 * LANES),
                                                            _INTERLEAVE))
            ptr = _element(context, builder, aryty, array, [item, zero])
            builder.store(both, builder.bitcast(
                ptr, ir.VectorType(_DOUBLE, 2 * LANES).as_pointer()), align=8)
        else:
            for col, v in ((zero, a), (one, b)):
                for k in range(LANES):
                    ptr = _element(context, builder, aryty, array,
                                   [builder.add(item, ir.Constant(item.type, k)), col])
                    builder.store(builder.extract_element(v, ir.Constant(_I32, k)), ptr)
        return context.get_dummy_value()
    return types.none(ary, item, first, second), codegen


@intrinsic
def gather_rows(typingctx, x, ids, item, slot):
    """The three coordinate vectors ``x[ids[item + k, slot], c]`` (c = 0, 1, 2; k the lane)
    of an (N, 3) float64 array ``x`` and an integer (n, m) array ``ids`` (connector ends,
    tet vertices), by scalar loads (module docstring)."""
    if not (_is_float_array(x, 2) and isinstance(ids, types.Array) and ids.ndim == 2
            and isinstance(ids.dtype, types.Integer)):
        return None

    def codegen(context, builder, sig, args):
        (xty, idty), (xv, idv, item, slot) = sig.args[:2], args
        xa = context.make_array(xty)(context, builder, xv)
        ia = context.make_array(idty)(context, builder, idv)
        slot = context.cast(builder, slot, sig.args[3], types.intp)
        item = context.cast(builder, item, sig.args[2], types.intp)
        coords = [ir.Constant(_V, ir.Undefined) for _ in range(3)]
        for k in range(LANES):
            row = builder.load(_element(context, builder, idty, ia,
                                        [builder.add(item, ir.Constant(item.type, k)), slot]))
            row = context.cast(builder, row, idty.dtype, types.intp)
            for c in range(3):
                ptr = _element(context, builder, xty, xa, [row, ir.Constant(row.type, c)])
                coords[c] = builder.insert_element(coords[c], builder.load(ptr),
                                                   ir.Constant(_I32, k))
        out = ir.Constant(context.get_value_type(sig.return_type), ir.Undefined)
        for c in range(3):
            out = builder.insert_value(out, _from_vector(builder, coords[c]), c)
        return out
    return types.UniTuple(VECTOR, 3)(x, ids, item, slot), codegen


@njit(cache=True)
def first_lane(mask):
    """The lowest set bit's position of a lane mask (> 0)."""
    k = 0
    while not (mask >> k) & 1:
        k += 1
    return k


@intrinsic
def vmax(typingctx, a, b):
    """Lane-wise ``a if a > b else b`` (a NaN lane of ``a`` gives ``b``)."""
    if a != VECTOR or b != VECTOR:
        return None

    def codegen(context, builder, sig, args):
        va, vb = _to_vector(builder, args[0]), _to_vector(builder, args[1])
        return _from_vector(builder, builder.select(builder.fcmp_ordered(">", va, vb), va, vb))
    return VECTOR(a, b), codegen


@njit(cache=True)
def arm_pair_lanes(r, c, prev, out, item, change):
    """Two Maxwell arms of items ``item .. item+LANES-1`` advanced lane-wise: ``out[k, a] =
    r[k, a] prev[k, a] + c[k, a] change_k`` (a = 0, 1; (n, 2) arrays, ``out`` may alias
    ``prev``: read first); returns the vector of ``out[k, 0] + out[k, 1]`` (the connectors'
    arm forces, the tets' arm pressures: the scalar recursions' operations, in order)."""
    r1, r2 = vload2(r, item)
    c1, c2 = vload2(c, item)
    p1, p2 = vload2(prev, item)
    p1 = vadd(vmul(r1, p1), vmul(c1, change))
    p2 = vadd(vmul(r2, p2), vmul(c2, change))
    vstore2(out, item, p1, p2)
    return vadd(p1, p2)


@njit(cache=True)
def all_inside(values, lo, hi, margin):
    """Whether every ``lo + margin < values <= hi - margin`` (1-d arrays; a NaN is not
    inside), lane-wise: the final-state checks' test of stored values against their range
    with room for the last step's change."""
    n = values.shape[0]
    rest = n // LANES * LANES
    inside = ALL_LANES
    m = vsplat(margin)
    for k in range(0, rest, LANES):
        v = vload(values, k)
        inside &= vlt_mask(vadd(vload(lo, k), m), v) & vle_mask(v, vsub(vload(hi, k), m))
    ok = inside == ALL_LANES
    for k in range(rest, n):
        ok &= (lo[k] + margin < values[k]) & (values[k] <= hi[k] - margin)
    return ok
