"""How Taichi's CPU backend addresses an item's columns, by the layout of the array (issue 43's addressing lever).

The robots schedule reads a link's or a voxel's row column by column from a flat buffer, ``buf[h[at] + i·W + c]``:
Taichi emits that index in i32 without a no-overflow flag, so LLVM cannot fold the static column ``c`` into the
address and every access pays its own ``lea`` + ``movslq`` (``docs/physics.md``, "Where the instructions go"). This
compiles one toy kernel — per item, 16 loads of one row (8 products of column c and c + 8) and one store — three
ways and counts the instructions of each in the printed assembly:

* ``flat``: a 1-D scalar buffer, ``buf[base + i·16 + c]`` (today's ``aos`` access);
* ``vec``: a 1-D buffer of 16-vectors, ``buf[base + i][c]`` (the row's address once, the columns as offsets);
* ``vec8``, ``vec4``: a 1-D buffer of 8- or 4-vectors, ``buf[base + i·16/L + c // L][c % L]`` (a row of 16 as
  16/L vectors: what a packed buffer of L-vectors, every table's width padded to a multiple of L, would give);
* ``twod``: a 2-D scalar buffer, ``buf[base + i, c]``;
* ``flat-gathered``, ``vec-gathered``: ``flat`` and ``vec`` with the item read from an index array, ``j = idx[i]``
  (as a link reads its voxels' rows: the real kernels' case), so LLVM knows nothing of ``j``'s range.

The loop counter ``i`` of the plain layouts is an induction variable whose range LLVM knows, so it can widen it to
64 bits and share one address between a row's columns; a gathered ``j`` gives it nothing to widen: there ``vec`` pays
what ``flat`` pays (measured in the real kernel too: ``docs/physics.md``).

    python scripts/probe_addressing.py      # ~15 s; the assembly is written in a temporary folder
"""

# (no `from __future__ import annotations` here: Taichi reads the annotations of kernel arguments)

import glob
import os
import re
import subprocess
import sys
import tempfile

WIDTH, PAIRS = 16, 8
LAYOUTS = ("flat", "vec", "vec8", "vec4", "twod", "flat-gathered", "vec-gathered")
COUNTED = ("movslq", "lea", "vmovss", "vfmadd", "vmul")


def child(layout: str) -> None:
    """Compile and run the toy kernel of ``layout`` once (the assembly goes to the current folder)."""
    import taichi as ti

    ti.init(arch=ti.cpu, print_kernel_asm=True, offline_cache=False, cpu_max_num_threads=1)
    Idx = ti.types.ndarray(dtype=ti.i32, ndim=1)
    if layout == "flat-gathered":
        buf = ti.ndarray(ti.f32, 100 * WIDTH)

        @ti.kernel
        def gathered(buf: ti.types.ndarray(dtype=ti.f32, ndim=1), idx: Idx, n: ti.i32):
            for _ in range(1):
                for i in range(n):
                    at, s = idx[i] * WIDTH, 0.0
                    for c in ti.static(range(PAIRS)):
                        s += buf[at + c] * buf[at + c + PAIRS]
                    buf[at + WIDTH - 1] = s
    elif layout == "vec-gathered":
        buf = ti.Vector.ndarray(WIDTH, ti.f32, 100)

        @ti.kernel
        def gathered(buf: ti.types.ndarray(dtype=ti.types.vector(WIDTH, ti.f32), ndim=1), idx: Idx, n: ti.i32):
            for _ in range(1):
                for i in range(n):
                    j, s = idx[i], 0.0
                    for c in ti.static(range(PAIRS)):
                        s += buf[j][c] * buf[j][c + PAIRS]
                    buf[j][WIDTH - 1] = s
    if layout.endswith("gathered"):
        gathered(buf, ti.ndarray(ti.i32, 10), 10)
        return
    if layout == "flat":
        buf = ti.ndarray(ti.f32, 100 * WIDTH)

        @ti.kernel
        def rows(buf: ti.types.ndarray(dtype=ti.f32, ndim=1), hdr: ti.types.ndarray(dtype=ti.i32, ndim=1), n: ti.i32):
            base = hdr[0]
            for _ in range(1):
                for i in range(n):
                    at, s = base + i * WIDTH, 0.0
                    for c in ti.static(range(PAIRS)):
                        s += buf[at + c] * buf[at + c + PAIRS]
                    buf[at + WIDTH - 1] = s
    elif layout == "vec":
        buf = ti.Vector.ndarray(WIDTH, ti.f32, 100)

        @ti.kernel
        def rows(buf: ti.types.ndarray(dtype=ti.types.vector(WIDTH, ti.f32), ndim=1),
                 hdr: ti.types.ndarray(dtype=ti.i32, ndim=1), n: ti.i32):
            base = hdr[0]
            for _ in range(1):
                for i in range(n):
                    s = 0.0
                    for c in ti.static(range(PAIRS)):
                        s += buf[base + i][c] * buf[base + i][c + PAIRS]
                    buf[base + i][WIDTH - 1] = s
    elif layout in ("vec4", "vec8"):
        lanes = 4 if layout == "vec4" else 8
        buf = ti.Vector.ndarray(lanes, ti.f32, 100 * WIDTH // lanes)

        @ti.kernel
        def rows(buf: ti.types.ndarray(dtype=ti.types.vector(lanes, ti.f32), ndim=1),
                 hdr: ti.types.ndarray(dtype=ti.i32, ndim=1), n: ti.i32):
            base = hdr[0]
            for _ in range(1):
                for i in range(n):
                    at, s = base + i * (WIDTH // lanes), 0.0
                    for c in ti.static(range(PAIRS)):
                        s += buf[at + c // lanes][c % lanes] * buf[at + (c + PAIRS) // lanes][(c + PAIRS) % lanes]
                    buf[at + (WIDTH - 1) // lanes][(WIDTH - 1) % lanes] = s
    else:
        buf = ti.ndarray(ti.f32, (100, WIDTH))

        @ti.kernel
        def rows(buf: ti.types.ndarray(dtype=ti.f32, ndim=2), hdr: ti.types.ndarray(dtype=ti.i32, ndim=1), n: ti.i32):
            base = hdr[0]
            for _ in range(1):
                for i in range(n):
                    s = 0.0
                    for c in ti.static(range(PAIRS)):
                        s += buf[base + i, c] * buf[base + i, c + PAIRS]
                    buf[base + i, WIDTH - 1] = s
    rows(buf, ti.ndarray(ti.i32, 1), 10)


def main() -> None:
    print(f"per layout, instructions in the toy kernel's assembly ({2 * PAIRS} loads and 1 store per item):")
    print("layout | " + " | ".join(COUNTED))
    for layout in LAYOUTS:
        with tempfile.TemporaryDirectory() as tmp:
            subprocess.run([sys.executable, os.path.abspath(__file__), "--child", layout], cwd=tmp, check=True,
                           capture_output=True)
            text = "".join(open(f).read() for f in glob.glob(os.path.join(tmp, "*asm*")))
        counts = [len(re.findall(rf"^\s+{op}", text, re.M)) for op in COUNTED]
        print(f"{layout} | " + " | ".join(str(c) for c in counts))


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--child":
        child(sys.argv[2])
    else:
        main()
