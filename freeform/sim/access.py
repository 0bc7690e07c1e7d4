"""How kernels reach the state: the precision's types and the memory order, both compile-time parameters.

``make_numbers(precision)``: the real type, 3- and 4-vectors of it, whether the arithmetic follows Voxelyze
exactly (f64), and ``nonfinite(x)``. ``make_access(order)``: the kernel-argument type of a ``state.Table`` and
``ld/st/get3/set3/get4/set4`` — the one place that knows the order:

* "soa": ``[columns, items]``; item i of column c at ``c·items + i``, so neighbouring threads read neighbouring
  addresses (the GPU's flat schedule);
* "aos": a 1-D ndarray of ``columns``-vectors, one item's columns together; the row length is a compile-time
  constant, so an item's address is computed once rather than per access (the CPU's per-robot schedule).
"""

# (no `from __future__ import annotations` here: Taichi reads the annotations of kernel arguments)

import functools
from types import SimpleNamespace

from freeform.sim.runtime import ti
from freeform.sim.state import F64, I32

ORDERS = ("soa", "aos")
PRECISIONS = ("f32", "f64")
# IEEE-754 exponent field: all ones means NaN or ±inf. Tested on the bits, as integers, because a float test
# (`x != x`, `not x <= big`) is exactly what fast-math's no-NaN/no-inf assumption lets the compiler fold away
# (Taichi's CUDA JIT enables it).
EXPONENT_MASK_F32 = 0x7F800000
EXPONENT_MASK_F64 = 0x7FF0000000000000


@functools.cache
def make_numbers(precision: str) -> SimpleNamespace:
    """Types and checks of "f32" | "f64" (explicit dtypes, so both precisions live in one process)."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    exact_vx = precision == "f64"
    real = ti.f64 if exact_vx else ti.f32
    bits = ti.i64 if exact_vx else ti.i32
    mask = EXPONENT_MASK_F64 if exact_vx else EXPONENT_MASK_F32

    @ti.func
    def nonfinite(x):
        """True for NaN and ±inf of this precision's real type (exponent bits all set)."""
        return (ti.bit_cast(x, bits) & bits(mask)) == bits(mask)

    return SimpleNamespace(precision=precision, real=real, vec3=ti.types.vector(3, real),
                           vec4=ti.types.vector(4, real), exact_vx=exact_vx, nonfinite=nonfinite)


def element_type(dtype: str, precision: str):
    """Taichi scalar type of a ``state.Table`` dtype at ``precision``."""
    if dtype == I32:
        return ti.i32
    return ti.f64 if dtype == F64 else make_numbers(precision).real


@functools.cache
def make_access(precision: str, order: str) -> SimpleNamespace:
    """Array argument types and accessors for memory ``order`` ("soa" | "aos")."""
    if order not in ORDERS:
        raise ValueError(f"order must be one of {ORDERS}, got {order!r}")
    aos = order == "aos"
    num = make_numbers(precision)

    def arg(table):
        """Kernel argument type of ``table``'s array: ``[columns, items]`` (soa), or ``[items]`` of
        ``columns``-vectors (aos)."""
        dtype = element_type(table.dtype, precision)
        if aos:
            return ti.types.ndarray(dtype=ti.types.vector(table.width, dtype), ndim=1)
        return ti.types.ndarray(dtype=dtype, ndim=2)

    def graph_arg(table, name: str):
        """The compute-graph placeholder (``ti.graph.Arg``) of an :func:`arg` of ``table`` named ``name``."""
        dtype = element_type(table.dtype, precision)
        if aos:
            return ti.graph.Arg(ti.graph.ArgKind.NDARRAY, name, dtype=dtype, ndim=1, element_shape=(table.width,))
        return ti.graph.Arg(ti.graph.ArgKind.NDARRAY, name, dtype=dtype, ndim=2)

    @ti.func
    def ld(a: ti.template(), c, i):
        if ti.static(aos):
            return a[i][c]
        else:
            return a[c, i]

    @ti.func
    def st(a: ti.template(), c: ti.template(), i, x):
        if ti.static(aos):
            a[i][c] = x
        else:
            a[c, i] = x

    @ti.func
    def get3(a: ti.template(), c: ti.template(), i):
        return num.vec3(ld(a, c, i), ld(a, c + 1, i), ld(a, c + 2, i))

    @ti.func
    def set3(a: ti.template(), c: ti.template(), i, x):
        st(a, c, i, x[0])
        st(a, c + 1, i, x[1])
        st(a, c + 2, i, x[2])

    @ti.func
    def get4(a: ti.template(), c: ti.template(), i):
        return num.vec4(ld(a, c, i), ld(a, c + 1, i), ld(a, c + 2, i), ld(a, c + 3, i))

    @ti.func
    def set4(a: ti.template(), c: ti.template(), i, x):
        st(a, c, i, x[0])
        st(a, c + 1, i, x[1])
        st(a, c + 2, i, x[2])
        st(a, c + 3, i, x[3])

    return SimpleNamespace(order=order, arg=arg, graph_arg=graph_arg, ld=ld, st=st, get3=get3, set3=set3, get4=get4, set4=set4)
