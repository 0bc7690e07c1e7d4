"""Can Taichi's CPU backend run a link update on 8 links at once? (issue 43's last lever, probed before building it)

Taichi 1.7 scalarises its vectors, and LLVM's loop vectoriser does not touch a kernel's outlined loop bodies, so the
simulator's kernels are scalar (docs/physics.md, "Vector units"). LLVM's SLP vectoriser, which packs isomorphic
scalar instructions of one basic block into SIMD ones, does run: a toy kernel over `vector(8)` rows comes out as
packed `ymm` arithmetic. So the question is whether a link update written for a group of 8 links — the same scalar
code for each lane, unrolled (``ti.static``), branch-free, the links' own state in lane-contiguous rows and the
voxels' poses gathered by index — is packed too, and what it saves against one link at a time.

The body is the heart of ``links.link_update`` (small-angle regime): both voxels' poses gathered, the separation
rotated into the negative voxel's frame, the relative rotation, the rotation vector by the f32 series, elastic and
damping loads, the loads rotated back, the link's state stored. Two kernels, the same arithmetic:

* ``per_link``: one link an iteration, its state in rows of the link (today's "aos" access);
* ``lanes``: a group of 8 links an iteration, each state column a row of 8 (one vector load a column).

Prints packed / scalar float instructions in each kernel's assembly and ns per link (one thread, best of 7 runs,
alternated), and checks that both kernels compute the same numbers.

    .venv/bin/python scripts/probe_simd_links.py [--quadrants]         # ~30 s (quadrants: its LLVM 22)
"""

# (no `from __future__ import annotations`: Taichi reads the annotations of its functions)
import re
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

LANES = 8
LINKS, VOXELS = 1 << 15, 1 << 14


def agree_of(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(a - b) / np.maximum(np.abs(b), 1.0)))


def main() -> None:
    asm_dir = Path(tempfile.mkdtemp(prefix="simd_asm_"))
    import os

    os.chdir(asm_dir)  # Taichi writes the printed assembly into the working directory
    import importlib

    ti = importlib.import_module("quadrants" if "--quadrants" in sys.argv else "taichi")

    ti.init(arch=ti.cpu, cpu_max_num_threads=1, fast_math=True, offline_cache=False, print_kernel_asm=True,
            log_level=ti.WARN)
    f32 = ti.f32
    # link state columns: L0, k_axial, b1, b2, b3, a2, damp, prev p2 (3), prev a2v (3) -> 13; outputs F_N, M_N, M_P (9)
    IN_COLS, OUT_COLS = 13, 9

    @ti.func
    def rotate(w, x, y, z, f0, f1, f2):
        """(w, x, y, z) f (w, x, y, z)* in Quat3D::RotateVec3D's arithmetic (quat.rotate's, on components)."""
        tw = f0 * x + f1 * y + f2 * z
        tx = f0 * w - f1 * z + f2 * y
        ty = f0 * z + f1 * w - f2 * x
        tz = -f0 * y + f1 * x + f2 * w
        return (w * tx + x * tw + y * tz - z * ty, w * ty - x * tz + y * tw + z * tx,
                w * tz + x * ty - y * tx + z * tw)

    def make_one_link(g: Callable, pack: Callable) -> Callable:
      @ti.func
      def one_link(pn, pp, qn, qp, c):
        """The small-angle link update of one link from its voxels' poses and its state columns c[j]."""
        # separation in the negative voxel's frame: rotate(conj(qn), pp - pn)
        w, x, y, z = g(qn, 0), -g(qn, 1), -g(qn, 2), -g(qn, 3)
        f = pp - pn
        f0, f1, f2 = g(f, 0), g(f, 1), g(f, 2)
        d0, d1, d2 = rotate(w, x, y, z, f0, f1, f2)
        # relative rotation q2 = conj(qn) * qp, its rotation vector by the f32 series (2·atan(|v|/w)/|v| · v)
        a, b, cc, e = g(qp, 0), g(qp, 1), g(qp, 2), g(qp, 3)
        q0 = w * a - x * b - y * cc - z * e
        q1 = w * b + x * a + y * e - z * cc
        q2 = w * cc - x * e + y * a + z * b
        q3 = w * e + x * cc - y * b + z * a
        inv = 1.0 / q0
        t2 = (q1 * q1 + q2 * q2 + q3 * q3) * inv * inv
        scale = 2.0 * inv * (1.0 - t2 * (1.0 / 3.0 - t2 * (0.2 - t2 / 7.0)))
        r0, r1, r2 = q1 * scale, q2 * scale, q3 * scale
        L0, kax, b1, b2, b3, a2, damp = g(c, 0), g(c, 1), g(c, 2), g(c, 3), g(c, 4), g(c, 5), g(c, 6)
        strain = (d0 - L0) / L0
        dp0, dp1, dp2 = 0.5 * (d0 - g(c, 7)), 0.5 * (d1 - g(c, 8)), 0.5 * (d2 - g(c, 9))
        da0, da1, da2 = 0.5 * (r0 - g(c, 10)), 0.5 * (r1 - g(c, 11)), 0.5 * (r2 - g(c, 12))
        fx = kax * strain + damp * dp0
        fy = b1 * d1 - b2 * r2 + damp * (b1 * dp1 - b2 * da2)
        fz = b1 * d2 + b2 * r1 + damp * (b1 * dp2 + b2 * da1)
        mx = a2 * r0 + damp * a2 * da0
        my = -b2 * d2 - b3 * r1 - damp * (b2 * dp2 + b3 * da1)
        mz = b2 * d1 - b3 * r2 - damp * (-b2 * dp1 + b3 * da2)
        # the positive end's moment, rotated back by conj(q2)
        p0, p1, p2 = rotate(q0, -q1, -q2, -q3, mx, my, mz)
        return pack([fx, fy, fz, mx, my, mz, p0, p1, p2])
      return one_link

    @ti.func
    def g_item(v, i: ti.template()):
        return v[i]

    @ti.func
    def g_row(v, i: ti.template()):
        return v[i, :]

    one_link = make_one_link(g_item, ti.Vector)
    one_link_rows = make_one_link(g_row, ti.Matrix.rows)

    vec3, vec4 = ti.types.vector(3, f32), ti.types.vector(4, f32)

    Cols = ti.types.vector(IN_COLS, f32)
    Outs = ti.types.vector(OUT_COLS, f32)
    Group = ti.types.matrix(IN_COLS, LANES, f32)  # a group's state: column j of lane l at [j, l] (rows of 8)
    GroupOut = ti.types.matrix(OUT_COLS, LANES, f32)

    @ti.kernel
    def per_link(pos: ti.types.ndarray(dtype=vec3, ndim=1), ori: ti.types.ndarray(dtype=vec4, ndim=1),
                 ends: ti.types.ndarray(dtype=ti.i32, ndim=2), state: ti.types.ndarray(dtype=Cols, ndim=1),
                 out: ti.types.ndarray(dtype=Outs, ndim=1)):
        for i in range(ends.shape[0]):
            n, p = ends[i, 0], ends[i, 1]
            out[i] = one_link(pos[n], pos[p], ori[n], ori[p], state[i])

    @ti.kernel
    def lanes(pos: ti.types.ndarray(dtype=vec3, ndim=1), ori: ti.types.ndarray(dtype=vec4, ndim=1),
              ends: ti.types.ndarray(dtype=ti.i32, ndim=3), state: ti.types.ndarray(dtype=Group, ndim=1),
              out: ti.types.ndarray(dtype=GroupOut, ndim=1)):
        for g in range(ends.shape[0]):
            S = state[g]
            R = GroupOut(0.0)
            for lane in ti.static(range(LANES)):
                n, p = ends[g, 0, lane], ends[g, 1, lane]
                r = one_link(pos[n], pos[p], ori[n], ori[p], ti.Vector([S[j, lane] for j in ti.static(range(IN_COLS))]))
                for j in ti.static(range(OUT_COLS)):
                    R[j, lane] = r[j]
            out[g] = R

    Poses = ti.types.matrix(14, LANES, f32)  # both ends' poses, already gathered into rows of 8

    @ti.kernel
    def lanes_gathered(poses: ti.types.ndarray(dtype=Poses, ndim=1), state: ti.types.ndarray(dtype=Group, ndim=1),
                       out: ti.types.ndarray(dtype=GroupOut, ndim=1)):
        for g in range(poses.shape[0]):
            S = state[g]
            P = poses[g]
            R = GroupOut(0.0)
            for lane in ti.static(range(LANES)):
                r = one_link(ti.Vector([P[0, lane], P[1, lane], P[2, lane]]), ti.Vector([P[3, lane], P[4, lane], P[5, lane]]),
                             ti.Vector([P[6, lane], P[7, lane], P[8, lane], P[9, lane]]),
                             ti.Vector([P[10, lane], P[11, lane], P[12, lane], P[13, lane]]),
                             ti.Vector([S[j, lane] for j in ti.static(range(IN_COLS))]))
                for j in ti.static(range(OUT_COLS)):
                    R[j, lane] = r[j]
            out[g] = R

    PoseRows = ti.types.matrix(3, LANES, f32)
    QuatRows = ti.types.matrix(4, LANES, f32)

    @ti.kernel
    def rows(poses: ti.types.ndarray(dtype=Poses, ndim=1), state: ti.types.ndarray(dtype=Group, ndim=1),
             out: ti.types.ndarray(dtype=GroupOut, ndim=1)):
        for g in range(poses.shape[0]):
            P = poses[g]
            pn = PoseRows([[P[i, ln] for ln in ti.static(range(LANES))] for i in ti.static(range(3))])
            pp = PoseRows([[P[3 + i, ln] for ln in ti.static(range(LANES))] for i in ti.static(range(3))])
            qn = QuatRows([[P[6 + i, ln] for ln in ti.static(range(LANES))] for i in ti.static(range(4))])
            qp = QuatRows([[P[10 + i, ln] for ln in ti.static(range(LANES))] for i in ti.static(range(4))])
            out[g] = one_link_rows(pn, pp, qn, qp, state[g])

    rng = np.random.default_rng(0)
    pos = rng.normal(size=(VOXELS, 3)).astype(np.float32)
    ori = rng.normal(size=(VOXELS, 4)).astype(np.float32) * 0.05
    ori[:, 0] = 1.0
    ori /= np.linalg.norm(ori, axis=1, keepdims=True)
    ends = rng.integers(0, VOXELS, size=(LINKS, 2)).astype(np.int32)
    ends = ends[np.argsort(ends[:, 0], kind="stable")]  # links come grouped by their voxels in the simulator
    state = rng.uniform(0.5, 1.5, size=(LINKS, IN_COLS)).astype(np.float32)
    out1 = np.zeros((LINKS, OUT_COLS), np.float32)
    groups = LINKS // LANES
    ends8 = np.ascontiguousarray(ends.reshape(groups, LANES, 2).transpose(0, 2, 1))
    state8 = np.ascontiguousarray(state.reshape(groups, LANES, IN_COLS).transpose(0, 2, 1))
    out8 = np.zeros((groups, OUT_COLS, LANES), np.float32)

    per_link(pos, ori, ends, state, out1)
    files = sorted(asm_dir.glob("*.s"))
    lanes(pos, ori, ends8, state8, out8)
    files_after = sorted(asm_dir.glob("*.s"))
    new = [f for f in files_after if f not in files]
    files_lanes = sorted(asm_dir.glob("*.s"))
    poses = np.concatenate([pos[ends[:, 0]], pos[ends[:, 1]], ori[ends[:, 0]], ori[ends[:, 1]]], axis=1)
    poses8 = np.ascontiguousarray(poses.reshape(groups, LANES, 14).transpose(0, 2, 1))
    outg = np.zeros_like(out8)
    lanes_gathered(poses8, state8, outg)
    gathered = [f for f in sorted(asm_dir.glob("*.s")) if f not in files_lanes]
    outr = np.zeros_like(out8)
    rows(poses8, state8, outr)
    by_rows = [f for f in sorted(asm_dir.glob("*.s")) if f not in files_lanes and f not in gathered]
    got = out8.transpose(0, 2, 1).reshape(LINKS, OUT_COLS)
    agree = max(agree_of(got, out1), agree_of(outg.transpose(0, 2, 1).reshape(LINKS, OUT_COLS), out1),
                agree_of(outr.transpose(0, 2, 1).reshape(LINKS, OUT_COLS), out1))

    def count(paths: list[Path]) -> tuple[int, int, int]:
        text = "".join(p.read_text() for p in paths)
        packed = len(re.findall(r"\bv(?:fn?m(?:add|sub)\d+|mul|add|sub|div|sqrt|max|min)ps\b", text))
        scalar = len(re.findall(r"\bv(?:fn?m(?:add|sub)\d+|mul|add|sub|div|sqrt|max|min)ss\b", text))
        return packed, scalar, len(re.findall(r"%ymm", text)) + len(re.findall(r"%zmm", text))

    best = {"per_link": np.inf, "lanes": np.inf, "lanes_gathered": np.inf, "rows": np.inf}
    for _ in range(7):
        for name, run in (("per_link", lambda: per_link(pos, ori, ends, state, out1)),
                          ("lanes", lambda: lanes(pos, ori, ends8, state8, out8)),
                          ("lanes_gathered", lambda: lanes_gathered(poses8, state8, outg)),
                          ("rows", lambda: rows(poses8, state8, outr))):
            t0 = time.perf_counter()
            for _ in range(20):
                run()
            ti.sync()
            best[name] = min(best[name], (time.perf_counter() - t0) / 20 / LINKS * 1e9)
    print(f"{ti.__name__} {ti.__version__}, one thread, {LINKS} links, fast-math; lanes against per-link: max rel. diff {agree:.1e}")
    for name, paths in (("per_link", files), ("lanes", new), ("lanes_gathered", gathered), ("rows", by_rows)):
        packed, scalar, wide = count(paths)
        print(f"  {name:14s} packed float ops {packed:4d}  scalar {scalar:4d}  ymm/zmm operands {wide:5d}  "
              f"{best[name]:6.2f} ns a link")


if __name__ == "__main__":
    sys.exit(main())
