"""Voxelyze's quaternion and link-frame arithmetic (``Quat3D.h``, spec sections 1 and 14) as Taichi functions.

Quaternions are (w, x, y, z) 4-vectors; ``qmul(a, b)`` is the Hamilton product "apply b, then a". In f64 every
function follows VX's arithmetic and thresholds (acos rotation vector with its small-angle shortcut). In f32 the
rotation vector uses the atan2 form, which has no dead zone where cos(θ/2) rounds to 1 (spec section 14), and a
series where that is exact to f32 rounding (``tests/test_sim_numerics.py`` pins both to scipy).
"""

# (no `from __future__ import annotations` here: Taichi reads the annotations of kernel arguments)

import functools
import math
from types import SimpleNamespace

from freeform.sim.access import make_numbers
from freeform.sim.runtime import ti

# Quat3D thresholds: FromRotationVector's |θ|⁴ below which it uses the Taylor form; ToRotationVector's sin²(θ/2)
# below which it uses its sqrt shortcut; FromAngleToPosX's |p.y/p.x|, |p.z/p.x| below which the rotation is
# linearised, and its distance from π beyond which p is taken as pointing along −x.
ROTVEC_SMALL4, TOROT_SMALL_SIN2, POSX_SMALL, POSX_PI_EPS = 5.328e-15, 2.4e-3, 1.732e-2, 1e-7
# f32 rotation vector: below this x² = (|xyz|/w)² (half-angle tan² 0.0256, a 0.32 rad bend) atan's series to x⁶
# is exact to f32 rounding (truncation x⁸/9 < 5e-8).
ATAN_SERIES_X2 = 0.0256


@functools.cache
def make_quat(precision: str) -> SimpleNamespace:
    """The quaternion functions of "f32" | "f64", and ``probe_rotations`` (a test hook kernel)."""
    num = make_numbers(precision)
    real, vec3, vec4, exact_vx = num.real, num.vec3, num.vec4, num.exact_vx

    @ti.func
    def qmul(a, b):
        """Hamilton product a*b ("apply b, then a")."""
        return vec4(
            a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
            a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
            a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
            a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0],
        )

    @ti.func
    def conj(q):
        return vec4(q[0], -q[1], -q[2], -q[3])

    @ti.func
    def rotate(q, f):
        """q f q* in Quat3D::RotateVec3D's arithmetic (also valid for a slightly non-unit q, as in VX)."""
        w, x, y, z = q[0], q[1], q[2], q[3]
        tw = f[0] * x + f[1] * y + f[2] * z
        tx = f[0] * w - f[1] * z + f[2] * y
        ty = f[0] * z + f[1] * w - f[2] * x
        tz = -f[0] * y + f[1] * x + f[2] * w
        return vec3(w * tx + x * tw + y * tz - z * ty, w * ty - x * tz + y * tw + z * tx,
                    w * tz + x * ty - y * tx + z * tw)

    @ti.func
    def to_axis_x(v, axis: ti.template()):
        """Permute a vector along link axis ``axis`` (0, 1, 2: compile-time) onto +x (VX toAxisX); for a quaternion
        pass its (x, y, z)."""
        r = v
        if ti.static(axis == 1):
            r = vec3(v[1], -v[0], v[2])
        elif ti.static(axis == 2):
            r = vec3(v[2], v[1], -v[0])
        return r

    @ti.func
    def to_axis_original(v, axis: ti.template()):
        """The inverse of ``to_axis_x``."""
        r = v
        if ti.static(axis == 1):
            r = vec3(-v[1], v[0], v[2])
        elif ti.static(axis == 2):
            r = vec3(-v[2], v[1], v[0])
        return r

    @ti.func
    def q_to_axis_x(q, axis: ti.template()):
        v = to_axis_x(vec3(q[1], q[2], q[3]), axis)
        return vec4(q[0], v[0], v[1], v[2])

    @ti.func
    def to_rotation_vector(q):
        """The rotation vector (axis · angle) of unit quaternion q."""
        r = vec3(0.0, 0.0, 0.0)
        xyz = vec3(q[1], q[2], q[3])
        if ti.static(exact_vx):
            w = q[0]
            if w < 1.0 and w > -1.0:
                sl = 1.0 - w * w
                if sl < TOROT_SMALL_SIN2:
                    r = 2.0 * xyz * ti.sqrt((2.0 - 2.0 * w) / sl)
                else:
                    r = 2.0 * xyz * ti.acos(w) / ti.sqrt(sl)
        else:
            # Links bend by well under 0.3 rad, so the common case uses the series of atan(x)/x in x² = s²/w²
            # (to x⁶), with no sqrt or atan2 call; atan2 beyond.
            w = q[0]
            s2 = xyz.dot(xyz)
            if w > 0.0 and s2 < ATAN_SERIES_X2 * w * w:
                iw = 1.0 / w
                x2 = s2 * iw * iw
                r = (2.0 * iw * (1.0 + x2 * (-1.0 / 3.0 + x2 * (1.0 / 5.0 - x2 * (1.0 / 7.0))))) * xyz
            elif s2 > 0.0:
                s = ti.sqrt(s2)
                r = 2.0 * ti.atan2(s, w) * xyz / s
        return r

    @ti.func
    def from_rotation_vector(v):
        """The unit quaternion of rotation vector v."""
        th = 0.5 * v
        a2 = th.dot(th)
        w = ti.cast(1.0, real)
        s = ti.cast(1.0, real)
        if a2 * a2 < ROTVEC_SMALL4:
            w = 1.0 - a2 / 2.0
            s = 1.0 - a2 / 6.0
        else:
            a = ti.sqrt(a2)
            w = ti.cos(a)
            s = ti.sin(a) / a
        return vec4(w, th[0] * s, th[1] * s, th[2] * s)

    @ti.func
    def from_angle_to_pos_x(p):
        """The rotation that takes p onto +x (Quat3D::FromAngleToPosX); identity for p = 0."""
        q = vec4(1.0, 0.0, 0.0, 0.0)
        if not (p[0] == 0.0 and p[1] == 0.0 and p[2] == 0.0):
            if p[0] != 0.0 and ti.abs(p[1] / p[0]) < POSX_SMALL and ti.abs(p[2] / p[0]) < POSX_SMALL:
                y = 0.5 * p[2] / p[0]
                z = -0.5 * p[1] / p[0]
                q = vec4(1.0 - 0.5 * (y * y + z * z), 0.0, y, z)
            else:
                n = p / p.norm()
                th = ti.acos(ti.min(ti.max(n[0], -1.0), 1.0))
                if th > math.pi - POSX_PI_EPS:
                    q = vec4(0.0, 0.0, 1.0, 0.0)
                else:
                    s = ti.sin(0.5 * th)
                    yz = ti.sqrt(n[1] * n[1] + n[2] * n[2])
                    q = vec4(ti.cos(0.5 * th), 0.0, n[2] * s / yz, -n[1] * s / yz)
        return q

    @ti.kernel
    def probe_rotations(q: ti.types.ndarray(dtype=vec4, ndim=1), rotvec: ti.types.ndarray(dtype=vec3, ndim=1),
                        back: ti.types.ndarray(dtype=vec4, ndim=1)):
        """Test hook: ToRotationVector of each q ``[n]`` and FromRotationVector of that (these very functions)."""
        for i in range(q.shape[0]):
            rotvec[i] = to_rotation_vector(q[i])
            back[i] = from_rotation_vector(rotvec[i])

    return SimpleNamespace(qmul=qmul, conj=conj, rotate=rotate, to_axis_x=to_axis_x, to_axis_original=to_axis_original,
                           q_to_axis_x=q_to_axis_x, to_rotation_vector=to_rotation_vector,
                           from_rotation_vector=from_rotation_vector, from_angle_to_pos_x=from_angle_to_pos_x,
                           probe_rotations=probe_rotations)
