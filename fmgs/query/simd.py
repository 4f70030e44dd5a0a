"""Explicit vector code for the text kernels (fmgs.query.kernels): one row of int8 codes dotted with
several texts' float32 weights, and a prefetch of a table's row.

Written from numba as plain loops, a row times T texts vectorises along the row and ends in T separate
horizontal sums; each costs a handful of shuffles, and for eight texts those sums, not the products,
bound the kernel. Here the products run in 16-lane vectors (one accumulator per text) and the T
accumulators are summed together by a transposing tree: pairs of vectors are interleaved and added
until one vector holds each text's total in its own lane (two shuffles per text for eight texts, against
four and a lane extract for a sum of its own).
For eight texts the bound's other terms (shift, error and residual norms, slack) also run as one
8-lane vector (``row_upper8``) rather than eight scalar epilogues, and the second tier's likewise
(``row_tier2_upper8``, its terms in float64). The narrowing (sparse rows, kernels.tier2_bounds) keeps its
scalar terms: its rows' reads, not its arithmetic, bound it. The figures that chose each of these:
benchmarks/results/TUNING.md.

Ranks must be multiples of ``LANES`` (the callers keep their loop for other ranks). The sums differ from
the loops' only in their order (float32, fused multiply-adds), which the kernels' slack already covers:
the twins in tests/query/test_kernels.py check both paths.

Selections (``compress_at_least``): the rows of a float32 vector at or above a cut, sixteen values per
compare, the positions of those that pass written by one masked compress store (AVX-512's vpcompressq;
LLVM emulates it elsewhere) and counted by a popcount: no branch per value (against numpy's compare and
flatnonzero: benchmarks/results/TUNING.md).

numba caches the kernels' machine code keyed on fmgs/query/kernels.py alone: after a change here, clear
fmgs/query/__pycache__ (or touch kernels.py) so they are compiled again.
"""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

LANES = 16
"""Lanes of the accumulators: one 512-bit register of float32 (two 256-bit ones where that is all)."""

_I32 = ir.IntType(32)
_F32 = ir.FloatType()
_F64 = ir.DoubleType()
_VEC = ir.VectorType(_F32, LANES)
_CODES = ir.VectorType(ir.IntType(8), LANES)


def _halves(width: int, group: int) -> tuple[list[int], list[int]]:
    """Lane indices of the first and second half of every ``group``-lane block of ``width`` lanes."""
    blocks = range(width // group)
    lo = [b * group + x for b in blocks for x in range(group // 2)]
    hi = [b * group + group // 2 + x for b in blocks for x in range(group // 2)]
    return lo, hi


def _fold(builder: ir.IRBuilder, a: ir.Value, b: ir.Value, width: int, group: int) -> ir.Value:
    """a and b (``width`` lanes in all: a's then b's) as blocks of ``group`` lanes, each block's two
    halves added: width // 2 lanes, each block's sum now in group // 2 lanes, blocks in order."""
    lo, hi = _halves(width, group)
    mask = lambda idx: ir.Constant(ir.VectorType(_I32, len(idx)), idx)  # noqa: E731
    return builder.fadd(builder.shuffle_vector(a, b, mask(lo)), builder.shuffle_vector(a, b, mask(hi)))


def transpose_sum(builder: ir.IRBuilder, vectors: list[ir.Value]) -> ir.Value:
    """The lane sums of T (a power of two <= LANES) vectors of LANES float32, as one vector of T lanes
    in order: sum(vectors[t]) in lane t."""
    group = LANES
    while len(vectors) > 1:  # adjacent vectors interleaved by half-blocks and added
        pairs = zip(vectors[::2], vectors[1::2], strict=True)
        vectors = [_fold(builder, a, b, 2 * LANES, group) for a, b in pairs]
        group //= 2
    v, width = vectors[0], LANES
    while group > 1:  # one vector left: its blocks' halves added
        v = _fold(builder, v, v, width, group)
        width //= 2
        group //= 2
    return v


def _row_sums(context, builder, types_, pairs, row, first, texts: int, tiers: int) -> ir.Value:
    """IR for the T = ``texts`` sums over ``tiers`` (codes, weights) pairs of a row: a <T x float>."""
    fma = cgutils.get_or_insert_function(
        builder.module, ir.FunctionType(_VEC, [_VEC, _VEC, _VEC]), "llvm.fma.v16f32"
    )
    accs = [cgutils.alloca_once_value(builder, ir.Constant(_VEC, [0.0] * LANES)) for _ in range(texts)]
    for tier in range(tiers):
        A = context.make_array(types_[2 * tier])(context, builder, pairs[2 * tier])
        W = context.make_array(types_[2 * tier + 1])(context, builder, pairs[2 * tier + 1])
        rank = cgutils.unpack_tuple(builder, A.shape, 2)[1]
        a_row = builder.gep(A.data, [builder.mul(row, cgutils.unpack_tuple(builder, A.strides, 2)[0])])
        w_rows = [
            builder.gep(W.data, [builder.mul(builder.add(first, ir.Constant(first.type, t)), rank)])
            for t in range(texts)
        ]
        chunks = builder.udiv(rank, ir.Constant(rank.type, LANES))
        with cgutils.for_range(builder, chunks) as loop:
            at = builder.mul(loop.index, ir.Constant(rank.type, LANES))
            codes = builder.load(builder.bitcast(builder.gep(a_row, [at]), _CODES.as_pointer()), align=1)
            x = builder.sitofp(builder.sext(codes, ir.VectorType(_I32, LANES)), _VEC)
            for t in range(texts):
                w_ptr = builder.bitcast(builder.gep(w_rows[t], [at]), _VEC.as_pointer())
                w = builder.load(w_ptr, align=4)
                builder.store(builder.call(fma, [x, w, builder.load(accs[t])]), accs[t])
    return transpose_sum(builder, [builder.load(a) for a in accs])


def _lanes(context, builder, signature, total: ir.Value, texts: int):
    lanes = [builder.extract_element(total, ir.Constant(_I32, t)) for t in range(texts)]
    return context.make_tuple(builder, signature.return_type, lanes)


def _row_dots_codegen(texts: int, tiers: int):
    def codegen(context, builder, signature, args):
        *pairs, row, first = args
        row = context.cast(builder, row, signature.args[-2], types.intp)
        first = context.cast(builder, first, signature.args[-1], types.intp)
        total = _row_sums(context, builder, signature.args, pairs, row, first, texts, tiers)
        return _lanes(context, builder, signature, total, texts)

    return codegen


def _splat(builder: ir.IRBuilder, x: ir.Value, vec: ir.VectorType) -> ir.Value:
    """The scalar x in every lane of ``vec``."""
    one = builder.insert_element(ir.Constant(vec, ir.Undefined), x, ir.Constant(_I32, 0))
    return builder.shuffle_vector(one, one, ir.Constant(ir.VectorType(_I32, vec.count), [0] * vec.count))


def _texts_of(context, builder, arr, typ, first: ir.Value, vec: ir.VectorType) -> ir.Value:
    """Elements first..first+T-1 of a C-contiguous 1-D array as one ``vec`` (T lanes), aligned only to
    its element."""
    a = context.make_array(typ)(context, builder, arr)
    ptr = builder.bitcast(builder.gep(a.data, [first]), vec.as_pointer())
    return builder.load(ptr, align=typ.dtype.bitwidth // 8)


def _row_upper_codegen(texts: int):
    """``row_upper8``: one tier's sums, then the bound's terms for the T texts as T-lane vector arithmetic
    (per text, the same operations in the same order as the scalar code it replaces)."""

    def codegen(context, builder, signature, args):
        A, W, row, first, shift, err, res, wn, vn, slack = args
        at = signature.args
        row = context.cast(builder, row, at[2], types.intp)
        first = context.cast(builder, first, at[3], types.intp)
        total = _row_sums(context, builder, at, [A, W], row, first, texts, 1)
        vec = ir.VectorType(_F32, texts)

        def row_of(arr, typ) -> ir.Value:
            a = context.make_array(typ)(context, builder, arr)
            return _splat(builder, builder.load(builder.gep(a.data, [row])), vec)

        def texts_of(arr, typ) -> ir.Value:
            return _texts_of(context, builder, arr, typ, first, vec)

        u = builder.fsub(total, row_of(shift, at[4]))
        u = builder.fadd(u, builder.fmul(row_of(err, at[5]), texts_of(wn, at[7])))
        u = builder.fadd(u, builder.fmul(row_of(res, at[6]), texts_of(vn, at[8])))
        u = builder.fadd(u, _splat(builder, context.cast(builder, slack, at[9], types.float32), vec))
        return _lanes(context, builder, signature, u, texts)

    return codegen


def _tier2_upper_codegen(texts: int):
    """``row_tier2_upper8``: three tables' sums, then the second tier's rounded-up bound for the T texts as
    T-lane float64 vector arithmetic (per text, kernels._up32's operations in its order)."""

    def codegen(context, builder, signature, args):
        at = signature.args
        *pairs, row, first, sh, e1, e2, res, wn1, wn2, vn2, slack = args
        row = context.cast(builder, row, at[6], types.intp)
        first = context.cast(builder, first, at[7], types.intp)
        total = _row_sums(context, builder, at, pairs, row, first, texts, 3)
        vec = ir.VectorType(_F64, texts)

        def splat(x: ir.Value) -> ir.Value:
            return _splat(builder, x, vec)

        def texts_of(arr, typ) -> ir.Value:
            return _texts_of(context, builder, arr, typ, first, vec)

        width = builder.fmul(splat(e1), texts_of(wn1, at[12]))
        width = builder.fadd(width, builder.fmul(splat(e2), texts_of(wn2, at[13])))
        width = builder.fadd(width, builder.fmul(splat(res), texts_of(vn2, at[14])))
        width = builder.fadd(width, splat(slack))
        u = builder.fadd(builder.fsub(builder.fpext(total, vec), splat(sh)), width)
        fabs = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(vec, [vec]), f"llvm.fabs.v{texts}f64"
        )
        up = builder.fmul(builder.call(fabs, [u]), splat(ir.Constant(_F64, 2.0**-22)))
        up = builder.fadd(builder.fadd(u, up), splat(ir.Constant(_F64, 1e-30)))
        return _lanes(context, builder, signature, builder.fptrunc(up, ir.VectorType(_F32, texts)), texts)

    return codegen


_I8P = ir.IntType(8).as_pointer()


def _prefetch_codegen(context, builder, signature, args):
    array, row = args
    A = context.make_array(signature.args[0])(context, builder, array)
    row = context.cast(builder, row, signature.args[1], types.intp)
    size = cgutils.unpack_tuple(builder, A.strides, signature.args[0].ndim)[0]  # bytes per row
    start = builder.gep(builder.bitcast(A.data, _I8P), [builder.mul(row, size)])
    # Unmangled: LLVM names the overload itself (typed and opaque pointers alike).
    fn = cgutils.get_or_insert_function(
        builder.module, ir.FunctionType(ir.VoidType(), [_I8P, _I32, _I32, _I32]), "llvm.prefetch"
    )
    hint = [ir.Constant(_I32, 0), ir.Constant(_I32, 3), ir.Constant(_I32, 1)]  # read, keep, data
    line = ir.Constant(size.type, 64)
    with builder.if_then(builder.icmp_signed(">", size, ir.Constant(size.type, 0))):
        lines = builder.udiv(builder.add(size, ir.Constant(size.type, 63)), line)
        with cgutils.for_range(builder, lines) as loop:  # a line per 64 bytes from the row's first byte
            builder.call(fn, [builder.gep(start, [builder.mul(loop.index, line)]), *hint])
        last = builder.gep(start, [builder.sub(size, ir.Constant(size.type, 1))])
        builder.call(fn, [last, *hint])  # and its last byte's (a row need not start a line)
    return context.get_dummy_value()


@intrinsic
def prefetch_row(typingctx, A, row):
    """Ask for row ``row`` of a C-contiguous array (an element of a 1-D one) to be brought into the cache,
    without waiting for it: a kernel reading rows in an order the hardware cannot guess (sorted but
    sparse rows of a memory-mapped table) issues it a few rows ahead so that the misses overlap its
    sums. Rows of zero bytes ask for nothing."""
    if not (isinstance(A, types.Array) and A.ndim in (1, 2) and A.layout == "C"):
        raise TypeError(f"prefetch_row wants a C-contiguous 1-D or 2-D array, got {A}")
    return types.void(A, row), _prefetch_codegen


def _check(pairs) -> None:
    for A, W in zip(pairs[::2], pairs[1::2], strict=True):
        ok = (
            isinstance(A, types.Array) and A.ndim == 2 and A.dtype == types.int8 and A.layout == "C"
            and isinstance(W, types.Array) and W.ndim == 2 and W.dtype == types.float32 and W.layout == "C"
        )  # fmt: skip
        if not ok:
            raise TypeError(f"row_dots wants C-contiguous int8 codes and float32 weights, got {A}, {W}")


def _check_vectors(name: str, dtype, *vectors) -> None:
    for v in vectors:
        if not (isinstance(v, types.Array) and v.ndim == 1 and v.dtype == dtype and v.layout == "C"):
            raise TypeError(f"{name} wants C-contiguous {dtype} vectors, got {v}")


@intrinsic
def row_dots8(typingctx, A, W, row, first):
    """(sum_j A[row,j] W[first+t,j] for t < 8) as float32; A [M,r] int8, W [n,r] float32, both
    C-contiguous, r a multiple of LANES."""
    _check((A, W))
    return types.UniTuple(types.float32, 8)(A, W, row, first), _row_dots_codegen(8, 1)


@intrinsic
def row_upper8(typingctx, A, W, row, first, shift, err, res, wn, vn, slack):
    """The first tier's upper bound on row ``row``'s margin for texts first..first+7 (kernels.int8_upper):
    sum_j A[row,j] W[first+t,j] - shift[row] + err[row] wn[first+t] + res[row] vn[first+t] + slack, t < 8,
    float32; shift, err, res [M] and wn, vn [n] C-contiguous float32, slack float32."""
    _check((A, W))
    _check_vectors("row_upper8", types.float32, shift, err, res, wn, vn)
    sig = types.UniTuple(types.float32, 8)(A, W, row, first, shift, err, res, wn, vn, slack)
    return sig, _row_upper_codegen(8)


@intrinsic
def row_dots4(typingctx, A, W, row, first):
    """``row_dots8`` for four texts."""
    _check((A, W))
    return types.UniTuple(types.float32, 4)(A, W, row, first), _row_dots_codegen(4, 1)


@intrinsic
def row_dots8x3(typingctx, A1, W1, A2, W2, A3, W3, row, first):
    """Three tables of a row's codes (the first tier, the second's head and tail): the sum over them of
    sum_j A[row,j] W[first+t,j], t < 8. A table may have no columns."""
    _check((A1, W1, A2, W2, A3, W3))
    return types.UniTuple(types.float32, 8)(A1, W1, A2, W2, A3, W3, row, first), _row_dots_codegen(8, 3)


@intrinsic
def row_dots4x3(typingctx, A1, W1, A2, W2, A3, W3, row, first):
    """``row_dots8x3`` for four texts."""
    _check((A1, W1, A2, W2, A3, W3))
    return types.UniTuple(types.float32, 4)(A1, W1, A2, W2, A3, W3, row, first), _row_dots_codegen(4, 3)


@intrinsic
def row_tier2_upper8(typingctx, A1, W1, A2, W2, A3, W3, row, first, sh, e1, e2, res, wn1, wn2, vn2, slack):
    """kernels.tier2_upper's bound for texts first..first+7 on row ``row``: u = a - sh + e1 wn1[first+t] +
    e2 wn2[first+t] + res vn2[first+t] + slack in float64 (a: ``row_dots8x3``'s float32 sum), returned
    as float32 rounded up, u + |u| 2^-22 + 1e-30; sh, e1, e2, res, slack float64, wn1, wn2, vn2 [n]
    C-contiguous float64."""
    _check((A1, W1, A2, W2, A3, W3))
    _check_vectors("row_tier2_upper8", types.float64, wn1, wn2, vn2)
    for x in (sh, e1, e2, res, slack):
        if x != types.float64:
            raise TypeError(f"row_tier2_upper8 wants float64 scalars, got {x}")
    sig = types.UniTuple(types.float32, 8)(
        A1, W1, A2, W2, A3, W3, row, first, sh, e1, e2, res, wn1, wn2, vn2, slack
    )
    return sig, _tier2_upper_codegen(8)


def _compress_codegen(context, builder, signature, args):
    x, at, cut, out, m = args
    xt, _, _, ot, _ = signature.args
    O = context.make_array(ot)(context, builder, out)
    at = context.cast(builder, at, signature.args[1], types.intp)
    m = context.cast(builder, m, signature.args[4], types.intp)
    vec = ir.VectorType(_F32, LANES)
    rows = ir.VectorType(ir.IntType(64), LANES)
    values = _texts_of(context, builder, x, xt, at, vec)
    cut = context.cast(builder, cut, signature.args[2], types.float32)
    keep = builder.fcmp_ordered(">=", values, _splat(builder, cut, vec))
    first = _splat(builder, builder.sext(at, ir.IntType(64)), rows)
    index = builder.add(first, ir.Constant(rows, list(range(LANES))))
    mask = ir.VectorType(ir.IntType(1), LANES)
    store = cgutils.get_or_insert_function(
        builder.module,
        ir.FunctionType(ir.VoidType(), [rows, ir.IntType(64).as_pointer(), mask]),
        f"llvm.masked.compressstore.v{LANES}i64",
    )
    builder.call(store, [index, builder.gep(O.data, [m]), keep])
    bits = builder.bitcast(keep, ir.IntType(LANES))
    popcount = cgutils.get_or_insert_function(
        builder.module, ir.FunctionType(ir.IntType(LANES), [ir.IntType(LANES)]), f"llvm.ctpop.i{LANES}"
    )
    return builder.zext(builder.call(popcount, [bits]), ir.IntType(64))


@intrinsic
def compress_at_least(typingctx, x, at, cut, out, m):
    """Of x[at:at+LANES] (float32, C-contiguous 1-D), the positions whose value is >= cut written to
    out[m:] (int64, in order); returns how many. Writes only those (out needs room for LANES more)."""
    _check_vectors("compress_at_least", types.float32, x)
    _check_vectors("compress_at_least", types.int64, out)
    return types.int64(x, at, cut, out, m), _compress_codegen
