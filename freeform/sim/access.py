"""How kernels reach the state: the precision's types and the memory order, both compile-time parameters.

``make_numbers(precision)``: the real type, 3- and 4-vectors of it, whether the arithmetic follows Voxelyze
exactly (f64), and ``nonfinite(x)``. ``make_access(order)``: the kernels' buffer arguments (``state.BUFFERS``, regions placed by ``packing.py``), the
``State`` bundle the physics funcs take, and ``ld/st/get3/set3/get4/set4`` — the one place that knows the order:

* "soa": ``[columns, items]``; item i of column c at ``c·stride + i``, so neighbouring threads read neighbouring
  addresses (the GPU's flat schedule);
* "aos": one item's columns together; the row length is a compile-time constant, so an item's address is
  computed once rather than per access (the CPU's per-robot schedule).
"""

# (no `from __future__ import annotations` here: Taichi reads the annotations of kernel arguments)

import functools
import warnings
from types import SimpleNamespace

from freeform.sim.runtime import ti
from freeform.sim.state import BUFFERS, F64, GP, HDR, I32, TABLES

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


class View:
    """One region of a buffer as the kernels see it (built while a kernel compiles; a template argument of the
    ``ti.func``s): the buffer, the header vector ``h`` loaded from it, and the static indices of this region's
    start and stride in ``h``. ``width`` and ``aos`` are compile-time constants."""

    def __init__(self, buf, h, name: str, width: int, aos: bool):
        self.buf, self.h, self.width, self.aos = buf, h, width, aos
        self.at, self.stride = getattr(HDR, f"{name.upper()}_AT"), getattr(HDR, f"{name.upper()}_STRIDE")


class State:
    """The whole simulation state by name, as one template argument: ``s.vr`` … ``s.lt`` (``state.TABLES``),
    ``s.gp`` (GP, item 0), ``s.hf`` (height grid, column 0), ``s.tr`` (the trace), ``s.h`` (the header) and
    ``s.sw`` (``state.Switches``, compile-time)."""

    def __init__(self, buffers: dict, h, sw, aos: bool):
        self.h, self.sw = h, sw
        for buffer, names in BUFFERS.items():
            for name in names:
                if name == "hdr":
                    continue
                table = TABLES.get(name)
                width = table.width if table is not None else (GP.width if name == "gp" else 1)
                setattr(self, name, View(buffers[buffer], h, name, width, aos and table is not None))


@functools.cache
def make_access(precision: str, order: str) -> SimpleNamespace:
    """The buffers' argument types and the accessors for memory ``order`` ("soa" | "aos"): ``header(ints)`` (a
    func: the header as a vector, loaded once per thread and item), ``bind(reals, ints, f64s, h, sw)`` (the
    ``State`` the physics funcs take) and ``ld/st/get3/set3/get4/set4`` on a ``View``."""
    if order not in ORDERS:
        raise ValueError(f"order must be one of {ORDERS}, got {order!r}")
    aos = order == "aos"
    num = make_numbers(precision)
    dtypes = {"reals": num.real, "ints": ti.i32, "f64s": ti.f64}
    Buffer = {name: ti.types.ndarray(dtype=dtype, ndim=1) for name, dtype in dtypes.items()}

    def graph_arg(buffer: str):
        """The compute-graph placeholder (``ti.graph.Arg``) of buffer argument ``buffer``."""
        return ti.graph.Arg(ti.graph.ArgKind.NDARRAY, buffer, dtype=dtypes[buffer], ndim=1)

    @ti.func
    def header(ints: ti.template()):
        return ti.Vector([ints[k] for k in ti.static(range(HDR.width))], dt=ti.i32)

    def bind(reals, ints, f64s, h, sw) -> State:
        """The ``State`` of these buffers; a plain Python call while the kernel compiles (it builds views and emits
        no code), which Taichi would warn about as a call it does not transform: that warning is silenced below."""
        return State({"reals": reals, "ints": ints, "f64s": f64s}, h, sw, aos)

    warnings.filterwarnings("ignore", message=r'.*Calling non-(taichi|quadrants) function "bind"',
                            category=SyntaxWarning)

    @ti.func
    def index(t: ti.template(), c, i):
        """Element of column ``c`` of item ``i`` in region ``t``."""
        at = 0
        if ti.static(t.aos):
            at = (t.h[t.at] + i * t.width) + c  # (the item's start is shared by all its columns' accesses)
        else:
            at = (t.h[t.at] + i) + c * t.h[t.stride]
        return at

    @ti.func
    def ld(t: ti.template(), c, i):
        return t.buf[index(t, c, i)]

    @ti.func
    def st(t: ti.template(), c, i, x):
        t.buf[index(t, c, i)] = x

    @ti.func
    def get3(t: ti.template(), c: ti.template(), i):
        return num.vec3(ld(t, c, i), ld(t, c + 1, i), ld(t, c + 2, i))

    @ti.func
    def set3(t: ti.template(), c: ti.template(), i, x):
        st(t, c, i, x[0])
        st(t, c + 1, i, x[1])
        st(t, c + 2, i, x[2])

    @ti.func
    def get4(t: ti.template(), c: ti.template(), i):
        return num.vec4(ld(t, c, i), ld(t, c + 1, i), ld(t, c + 2, i), ld(t, c + 3, i))

    @ti.func
    def set4(t: ti.template(), c: ti.template(), i, x):
        st(t, c, i, x[0])
        st(t, c + 1, i, x[1])
        st(t, c + 2, i, x[2])
        st(t, c + 3, i, x[3])

    return SimpleNamespace(order=order, Buffer=Buffer, graph_arg=graph_arg, header=header, bind=bind, ld=ld, st=st,
                           get3=get3, set3=set3, get4=get4, set4=set4)


@functools.cache
def make_transfers() -> SimpleNamespace:
    """``read(buf, at, step, n, out)`` and ``write(buf, at, step, n, src)``: copy ``n`` elements
    ``buf[at + i·step]`` to or from a staging array, so the host moves one region (step 1) or one column of a
    table (a column is strided in "aos"), not a whole buffer (compiled per dtype)."""

    @ti.kernel
    def read(buf: ti.types.ndarray(ndim=1), at: ti.i32, step: ti.i32, n: ti.i32, out: ti.types.ndarray(ndim=1)):
        for i in range(n):
            out[i] = buf[at + i * step]

    @ti.kernel
    def write(buf: ti.types.ndarray(ndim=1), at: ti.i32, step: ti.i32, n: ti.i32, src: ti.types.ndarray(ndim=1)):
        for i in range(n):
            buf[at + i * step] = src[i]

    return SimpleNamespace(read=read, write=write)
