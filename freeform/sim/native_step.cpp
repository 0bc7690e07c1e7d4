// The CPU simulator's step in C++: the native schedule (freeform/sim/native.py; docs/physics.md, "The native
// schedule"; issues 43 and 58).
//
// The same arithmetic as freeform/sim/links.py, voxels.py and quat.py on the f32 path — Voxelyze semantics, fixed
// dt (no rl4design slips, no omega^2 store), any actuation, the flat floor or none — on the engine's own packed
// buffers; the column indices and widths come from freeform/sim/state.py through the generated layout.h
// (native.layout_header), so this file never spells an offset. The link tables are read column by column (copied
// so around each robot's steps: this code's own layout, which makes a column of a group's consecutive links one
// vector load); the voxel rows stay the engine's and are gathered.
//
// *_scalar: every item with Voxelyze's branches (link_update, voxel_update).
// *_vector: a group of LANES items at once (link_group, voxel_group: GCC's vector extensions, one source of the
// math templated on the lane type, LANES following the target) along the common path, and every lane off it again
// by the branching update, before anything of that lane is stored. A link's common path: the small angle, its end
// rotation within atan's series; a voxel's: not held fixed, no snapshot this step (its rotation's cos and sin, and
// its Poisson strain's pow, are glibc's vector maths where a lane needs them: libmvec's _ZGVeN16v_ / _ZGVdN8v_
// variants).
#include <cfloat>
#include <cmath>
#include <cstdint>
#include <algorithm>
#include <atomic>
#include <condition_variable>
#include <cstring>
#include <functional>
#include <mutex>
#if defined(__AVX2__) || defined(__AVX512F__)
#include <immintrin.h>
#endif
#include <thread>
#include <type_traits>
#include <unistd.h>
#include <vector>

#include "layout.h"

namespace {

// The lanes of a group follow the target's vector registers: 16 floats in AVX-512's, 8 in AVX2's, 4 otherwise (SSE,
// NEON: GCC's generic vectors, plain loops where x86 has an instruction). -DNATIVE_LANES=n overrides (a group wider
// than the registers runs in pieces: the AVX2 build did so before it had its own width, 1.8x slower than Taichi's
// step; lab/notes/2026-11-28-native-avx2.md).
#if defined(NATIVE_LANES)
#define LANE_COUNT NATIVE_LANES
#elif defined(__AVX512F__)
#define LANE_COUNT 16
#elif defined(__AVX2__)
#define LANE_COUNT 8
#else
#define LANE_COUNT 4
#endif
#if defined(__AVX512F__) && LANE_COUNT == 16
#define ISA_AVX512 1
#elif defined(__AVX2__) && LANE_COUNT == 8
#define ISA_AVX2 1
#endif
constexpr int LANES = LANE_COUNT;
typedef float vf __attribute__((vector_size(4 * LANES)));
typedef int32_t vi __attribute__((vector_size(4 * LANES)));

template <class F> struct V3 { F x, y, z; };
template <class F> struct Q4 { F w, x, y, z; };

template <class F> inline V3<F> operator+(V3<F> a, V3<F> b) { return {a.x + b.x, a.y + b.y, a.z + b.z}; }
template <class F> inline V3<F> operator-(V3<F> a, V3<F> b) { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
template <class S, class F> inline V3<F> operator*(S s, V3<F> a) { return {s * a.x, s * a.y, s * a.z}; }
template <class F> inline V3<F> neg(V3<F> a) { return {-a.x, -a.y, -a.z}; }

template <class F> inline Q4<F> qmul(Q4<F> a, Q4<F> b) {
  return {a.w * b.w - a.x * b.x - a.y * b.y - a.z * b.z, a.w * b.x + a.x * b.w + a.y * b.z - a.z * b.y,
          a.w * b.y - a.x * b.z + a.y * b.w + a.z * b.x, a.w * b.z + a.x * b.y - a.y * b.x + a.z * b.w};
}
template <class F> inline Q4<F> conj(Q4<F> q) { return {q.w, -q.x, -q.y, -q.z}; }

// q f q* in Quat3D::RotateVec3D's arithmetic
template <class F> inline V3<F> rotate(Q4<F> q, V3<F> f) {
  F tw = f.x * q.x + f.y * q.y + f.z * q.z;
  F tx = f.x * q.w - f.y * q.z + f.z * q.y;
  F ty = f.x * q.z + f.y * q.w - f.z * q.x;
  F tz = -f.x * q.y + f.y * q.x + f.z * q.w;
  return {q.w * tx + q.x * tw + q.y * tz - q.z * ty, q.w * ty - q.x * tz + q.y * tw + q.z * tx,
          q.w * tz + q.x * ty - q.y * tx + q.z * tw};
}

// select per lane: m (int or a vector of lane masks) ? a : b
inline float sel(int m, float a, float b) { return m ? a : b; }
inline vf sel(vi m, vf a, vf b) { return m ? a : b; }
inline vi sel(vi m, vi a, vi b) { return m ? a : b; }
template <class M, class F> inline V3<F> sel(M m, V3<F> a, V3<F> b) {
  return {sel(m, a.x, b.x), sel(m, a.y, b.y), sel(m, a.z, b.z)};
}
inline float fabs_(float x) { return std::fabs(x); }
inline vf fabs_(vf x) { return (vf)((vi)x & 0x7FFFFFFF); }

// VX toAxisX / toAxisOriginal for a link along x (0), y (1) or z (2); y, z: the lane's axis is 1, 2
template <class M, class F> inline V3<F> to_axis_x(V3<F> v, M y, M z) {  // y: (v.y, -v.x, v.z); z: (v.z, v.y, -v.x)
  return {sel(y, v.y, sel(z, v.z, v.x)), sel(y, -v.x, v.y), sel(z, -v.x, v.z)};
}
template <class M, class F> inline V3<F> to_axis_original(V3<F> v, M y, M z) {  // y: (-v.y, v.x, v.z); z: (-v.z, v.y, v.x)
  return {sel(y, -v.y, sel(z, -v.z, v.x)), sel(y, v.x, v.y), sel(z, v.x, v.z)};
}
template <class M, class F> inline Q4<F> q_to_axis_x(Q4<F> q, M y, M z) {
  V3<F> v = to_axis_x(V3<F>{q.x, q.y, q.z}, y, z);
  return {q.w, v.x, v.y, v.z};
}

// the f32 rotation vector's series (quat.py): 2·atan(|xyz|/w)/|xyz| to x^6 in x^2 = |xyz|^2/w^2
template <class F> inline V3<F> rotation_vector_series(Q4<F> q) {
  const F iw = 1.0f / q.w, x2 = (q.x * q.x + q.y * q.y + q.z * q.z) * iw * iw;
  const F k = 2.0f * iw * (1.0f + x2 * (-1.0f / 3.0f + x2 * (1.0f / 5.0f - x2 * (1.0f / 7.0f))));
  return {k * q.x, k * q.y, k * q.z};
}
template <class F> inline auto series_applies(Q4<F> q) {
  return (q.w > 0.0f) & ((q.x * q.x + q.y * q.y + q.z * q.z) < ATAN_SERIES_X2 * q.w * q.w);
}

// ---- one link, with Voxelyze's branches (links.py:link_update) ----

inline V3<float> to_rotation_vector(Q4<float> q) {
  if (series_applies(q)) return rotation_vector_series(q);
  const float s2 = q.x * q.x + q.y * q.y + q.z * q.z;
  if (!(s2 > 0.0f)) return {0.0f, 0.0f, 0.0f};
  const float s = std::sqrt(s2), k = 2.0f * std::atan2(s, q.w) / s;
  return {k * q.x, k * q.y, k * q.z};
}

// Quat3D::FromAngleToPosX: the rotation that takes p onto +x
inline Q4<float> from_angle_to_pos_x(V3<float> p) {
  if (p.x == 0.0f && p.y == 0.0f && p.z == 0.0f) return {1.0f, 0.0f, 0.0f, 0.0f};
  if (p.x != 0.0f && std::fabs(p.y / p.x) < POSX_SMALL && std::fabs(p.z / p.x) < POSX_SMALL) {
    const float y = 0.5f * p.z / p.x, z = -0.5f * p.y / p.x;
    return {1.0f - 0.5f * (y * y + z * z), 0.0f, y, z};
  }
  const V3<float> n = (1.0f / std::sqrt(p.x * p.x + p.y * p.y + p.z * p.z)) * p;
  const float th = std::acos(std::fmin(std::fmax(n.x, -1.0f), 1.0f));
  if (th > float(M_PI - POSX_PI_EPS)) return {0.0f, 0.0f, 1.0f, 0.0f};
  const float s = std::sin(0.5f * th), yz = std::sqrt(n.y * n.y + n.z * n.z);
  return {std::cos(0.5f * th), 0.0f, n.z * s / yz, -n.y * s / yz};
}

struct Regions {
  float* __restrict vr;
  float* __restrict lr;  // column by column: link lk's column c at c·links + lk
  const float *__restrict mt, *__restrict lt;
  int32_t* __restrict vi;
  int32_t* __restrict li;  // column by column
  int links;
};

inline V3<float> get3(const float* base, int at) { return {base[at], base[at + 1], base[at + 2]}; }
inline Q4<float> get4(const float* base, int at) { return {base[at], base[at + 1], base[at + 2], base[at + 3]}; }

// Link lk's update (steps 1-8); returns 1 if its strain diverged.
inline int link_update(const Regions& s, int lk, float prev_dt, float max_strain) {
  const int L = s.links;
  const int n = s.li[lk + LI_NEG * L], p = s.li[lk + LI_POS * L], axis = s.li[lk + LI_AXIS * L];
  const int flags = s.li[lk + LI_FLAGS * L], vn = n * VR_W, vp = p * VR_W, lt = s.li[lk + LI_LMAT * L] * LT_W;
  const int ay = axis == 1, az = axis == 2;
  bool valid = flags & FLAG_VALID, small = flags & FLAG_SMALL;
  const float L0 = 0.5f * (s.vr[vn + VR_SIZE] + s.vr[vp + VR_SIZE]);
  // 1. orientLink
  Q4<float> q1 = q_to_axis_x(get4(s.vr, vn + VR_ORI), ay, az), q2 = q_to_axis_x(get4(s.vr, vp + VR_ORI), ay, az);
  const Q4<float> R = conj(q1);
  V3<float> pos2 = rotate(R, to_axis_x(get3(s.vr, vp + VR_POS) - get3(s.vr, vn + VR_POS), ay, az));
  q2 = qmul(R, q2);
  const float area = 0.5f * (s.vr[vn + VR_TAREA + axis] + s.vr[vp + VR_TAREA + axis]);
  const float ssum = 0.5f * (s.vr[vn + VR_TSUM + axis] + s.vr[vp + VR_TSUM + axis]);
  const float small_turn = (std::fabs(pos2.z) + std::fabs(pos2.y)) / pos2.x, extend = std::fabs(1.0f - pos2.x / L0);
  const bool leave = small && (small_turn > HYST * SA_BEND || extend > HYST * SA_EXT);
  if (!small && small_turn < SA_BEND && extend < SA_EXT) {
    small = true;
    valid = false;
  } else if (leave) {
    small = false;
    valid = false;
  }
  q1 = {1.0f, 0.0f, 0.0f, 0.0f};
  V3<float> a1v = {0.0f, 0.0f, 0.0f};
  if (small) {
    pos2.x -= L0;
  } else {
    q1 = from_angle_to_pos_x(pos2);
    q2 = qmul(q1, q2);
    pos2 = {std::sqrt(pos2.x * pos2.x + pos2.y * pos2.y + pos2.z * pos2.z) - L0, 0.0f, 0.0f};
    a1v = to_rotation_vector(q1);
  }
  const V3<float> a2v = to_rotation_vector(q2);
  const float strain = pos2.x / L0;
  // 2. half the change since the last step
  const V3<float> P2o = {s.lr[lk + LR_P2 * L], s.lr[lk + (LR_P2 + 1) * L], s.lr[lk + (LR_P2 + 2) * L]};
  const V3<float> A1o = {s.lr[lk + LR_A1 * L], s.lr[lk + (LR_A1 + 1) * L], s.lr[lk + (LR_A1 + 2) * L]};
  const V3<float> A2o = {s.lr[lk + LR_A2 * L], s.lr[lk + (LR_A2 + 1) * L], s.lr[lk + (LR_A2 + 2) * L]};
  const V3<float> dP = 0.5f * (pos2 - P2o), dA1 = 0.5f * (a1v - A1o), dA2 = 0.5f * (a2v - A2o);
  // 3.-4. stress
  const float nu = s.lt[lt + LT_NU];
  const float stress = nu != 0.0f ? s.lt[lt + LT_EHAT] * ((1.0f - nu) * strain + nu * ssum) : s.lt[lt + LT_E] * strain;
  // 5. elastic loads
  const float b1 = s.lt[lt + LT_B1], b2 = s.lt[lt + LT_B2], b3 = s.lt[lt + LT_B3], a2 = s.lt[lt + LT_A2];
  V3<float> fN = {stress * area, b1 * pos2.y - b2 * (a1v.z + a2v.z), b1 * pos2.z + b2 * (a1v.y + a2v.y)};
  V3<float> fP = neg(fN);
  V3<float> mN = {a2 * (a2v.x - a1v.x), -b2 * pos2.z - b3 * (2.0f * a1v.y + a2v.y), b2 * pos2.y - b3 * (2.0f * a1v.z + a2v.z)};
  V3<float> mP = {a2 * (a1v.x - a2v.x), -b2 * pos2.z - b3 * (a1v.y + 2.0f * a2v.y), b2 * pos2.y - b3 * (a1v.z + 2.0f * a2v.z)};
  // 6. internal damping, unless a regime switch invalidated the rates
  if (valid) {
    const float dN = s.mt[s.vi[n * VI_W + VI_MAT] * MT_W + MT_DAMP] / prev_dt;
    const float dPp = s.mt[s.vi[p * VI_W + VI_MAT] * MT_W + MT_DAMP] / prev_dt;
    const float sqA1 = s.lt[lt + LT_SQA1], sqA2xIp = s.lt[lt + LT_SQA2XIP], sqB1 = s.lt[lt + LT_SQB1],
                sqB2xFMp = s.lt[lt + LT_SQB2XFMP], sqB3xIp = s.lt[lt + LT_SQB3XIP];
    const V3<float> c = {sqA1 * dP.x, sqB1 * dP.y - sqB2xFMp * (dA1.z + dA2.z), sqB1 * dP.z + sqB2xFMp * (dA1.y + dA2.y)};
    fN = fN + dN * c;
    fP = fP - dPp * c;
    mN = mN - (0.5f * dN) * V3<float>{-sqA2xIp * (dA2.x - dA1.x), sqB2xFMp * dP.z + sqB3xIp * (2.0f * dA1.y + dA2.y),
                                      -sqB2xFMp * dP.y + sqB3xIp * (2.0f * dA1.z + dA2.z)};
    mP = mP - (0.5f * dPp) * V3<float>{sqA2xIp * (dA2.x - dA1.x), sqB2xFMp * dP.z + sqB3xIp * (dA1.y + 2.0f * dA2.y),
                                       -sqB2xFMp * dP.y + sqB3xIp * (dA1.z + 2.0f * dA2.z)};
  }
  valid = true;
  // 7. into each end's voxel frame, then the link's axis
  if (!small) {
    fN = rotate(conj(q1), fN);
    mN = rotate(conj(q1), mN);
  }
  fP = rotate(conj(q2), fP);
  mP = rotate(conj(q2), mP);
  const V3<float> out[7] = {to_axis_original(fN, ay, az), to_axis_original(fP, ay, az), to_axis_original(mN, ay, az),
                            to_axis_original(mP, ay, az), pos2, a1v, a2v};
  const int col[7] = {LR_FN, LR_FP, LR_MN, LR_MP, LR_P2, LR_A1, LR_A2};
  for (int j = 0; j < 7; ++j) {
    s.lr[lk + col[j] * L] = out[j].x;
    s.lr[lk + (col[j] + 1) * L] = out[j].y;
    s.lr[lk + (col[j] + 2) * L] = out[j].z;
  }
  s.lr[lk + LR_STRAIN * L] = strain;
  s.li[lk + LI_FLAGS * L] = (small ? FLAG_SMALL : 0) | (valid ? FLAG_VALID : 0);
  // 8. divergence (by the exponent bits: -ffast-math would fold a floating-point test for NaN away)
  uint32_t bits;
  std::memcpy(&bits, &strain, 4);
  return strain > max_strain || (bits & 0x7F800000u) == 0x7F800000u;
}

// ---- one voxel, with Voxelyze's branches (voxels.py:voxel_update, flat floor, the sine's actuation) ----

struct Robot {  // what a voxel reads of its robot and the batch, this step
  float dt, sin, cos, temp_amp;
  int events;
  int floor;    // Switches.floor: contact with the ground on
  int command;  // Switches.command: 0 the sine, 1 each voxel's command, 2 the sine plus the command (clipped)
  int ramping;  // a command ramp in progress (RT.RAMP): the command moves from CMD0 to CMD, `blend` of the way
  float blend;
};

inline Q4<float> from_rotation_vector(V3<float> v) {
  const V3<float> th = 0.5f * v;
  const float a2 = th.x * th.x + th.y * th.y + th.z * th.z;
  float w, k;
  if (a2 * a2 < ROTVEC_SMALL4) {
    w = 1.0f - a2 / 2.0f;
    k = 1.0f - a2 / 6.0f;
  } else {
    const float a = std::sqrt(a2);
    w = std::cos(a);
    k = std::sin(a) / a;
  }
  return {w, th.x * k, th.y * k, th.z * k};
}

inline Q4<float> renormalise(Q4<float> q) {
  const float n2 = q.w * q.w + q.x * q.x + q.y * q.y + q.z * q.z;
  const float k = std::fabs(n2 - 1.0f) < RENORM_NEWTON ? 1.5f - 0.5f * n2 : 1.0f / std::sqrt(n2);
  return {q.w * k, q.x * k, q.y * k, q.z * k};
}

// the voxel's strain along each axis from its links' strains (voxels.py:poisson_strain)
inline V3<float> poisson_strain(const Regions& s, int v, int mat) {
  const float* m = s.mt + mat * MT_W;
  const float nu = m[MT_NU];
  float strain[3] = {0.0f, 0.0f, 0.0f};
  if (nu == 0.0f) return {0.0f, 0.0f, 0.0f};
  int tension[3] = {0, 0, 0};
  const int L = s.links;
  for (int a = 0; a < 3; ++a) {
    int cnt = 0;
    for (int side = 0; side < 2; ++side) {
      const int lk = s.vi[v * VI_W + VI_SLOT + 2 * a + side];
      if (lk >= 0) {
        const float eps = s.lr[lk + LR_STRAIN * L];
        strain[a] += eps * s.lt[s.li[lk + LI_LMAT * L] * LT_W + (side == 1 ? LT_PSPOS : LT_PSNEG)];
        ++cnt;
      }
    }
    if (cnt == 2) {
      strain[a] *= 0.5f;
      tension[a] = 1;
    }
  }
  if (!(tension[0] && tension[1] && tension[2])) {
    float add = 0.0f;
    for (int a = 0; a < 3; ++a)
      if (tension[a]) add += strain[a];
    float val;
    if (std::fabs(add) < POISSON_SERIES_X) {
      float c = m[MT_PB1 + POISSON_SERIES_TERMS - 1];
      for (int k = POISSON_SERIES_TERMS - 1; k > 0; --k) c = m[MT_PB1 + k - 1] + add * c;
      val = add * c;
    } else {
      val = std::pow(1.0f + add, -nu) - 1.0f;
    }
    for (int a = 0; a < 3; ++a)
      if (!tension[a]) strain[a] = val;
  }
  return {strain[0], strain[1], strain[2]};
}

inline void set3(float* base, int at, V3<float> v) { base[at] = v.x; base[at + 1] = v.y; base[at + 2] = v.z; }

// What drives a voxel's temperature (voxels.py:temperature): the sine, its command, or the sine corrected by the
// command and kept in the sine's range; a ramping command moves from the one before (voxels.py's arithmetic)
template <class F> inline F wave(const Robot& rb, F cmd, F cmd0, F sine) {
  if (rb.command == 0) return sine;
  const F command = rb.ramping ? cmd0 + (cmd - cmd0) * rb.blend : cmd;
  if (rb.command == 1) return command;
  const F w = sine + command;
  return w < -1.0f ? F{} - 1.0f : (w > 1.0f ? F{} + 1.0f : w);
}

// Voxel v's update (spec sections 6-9); returns 1 if its pose became non-finite.
inline int voxel_update(const Regions& s, int v, const Robot& rb) {
  const int row = v * VR_W, L = s.links;
  const int mat = s.vi[v * VI_W + VI_MAT];
  int flags = s.vi[v * VI_W + VI_FLAGS];
  const float* m = s.mt + mat * MT_W;
  const float minv = m[MT_MINV], iinv = m[MT_IINV], dt = rb.dt;
  V3<float> pos = get3(s.vr, row + VR_POS), mom = get3(s.vr, row + VR_MOM), amom = get3(s.vr, row + VR_AMOM);
  Q4<float> q = get4(s.vr, row + VR_ORI);
  const float size = s.vr[row + VR_SIZE];
  const V3<float> ps = poisson_strain(s, v, mat);
  if (flags & FLAG_FIXED) {
    pos = get3(s.vr, row + VR_POS0);
    mom = amom = {0.0f, 0.0f, 0.0f};
    q = {1.0f, 0.0f, 0.0f, 0.0f};
  } else {
    V3<float> force = {0.0f, 0.0f, 0.0f}, moment = {0.0f, 0.0f, 0.0f};
    for (int d = 0; d < 6; ++d) {
      const int lk = s.vi[v * VI_W + VI_SLOT + d];
      if (lk >= 0) {
        const int f = d % 2 == 1 ? LR_FP : LR_FN, mm = d % 2 == 1 ? LR_MP : LR_MN;
        force = force + V3<float>{s.lr[lk + f * L], s.lr[lk + (f + 1) * L], s.lr[lk + (f + 2) * L]};
        moment = moment + V3<float>{s.lr[lk + mm * L], s.lr[lk + (mm + 1) * L], s.lr[lk + (mm + 2) * L]};
      }
    }
    const V3<float> vel = minv * mom;
    force = rotate(q, force) - m[MT_CG] * vel;
    force.z += m[MT_MG];
    moment = rotate(q, moment) - m[MT_CGR] * (iinv * amom);
    bool stat = flags & FLAG_STATIC;
    // the flat floor (voxels.py:flat_floor_step, floor_force)
    const float pen = 0.5f * size - 0.5f * m[MT_L] - pos.z;
    V3<float> fric = {0.0f, 0.0f, 0.0f};
    if (!rb.floor) {
      // (no ground: no contact force, and static is cleared below)
    } else if (pen >= 0.0f) {
      const float normal = m[MT_KPEN] * pen;
      force.z += normal - m[MT_CC] * vel.z;
      if (stat) {
        const float mus = m[MT_MUS] * normal;
        if (force.x * force.x + force.y * force.y > mus * mus) stat = false;
      } else {
        const float vh = std::sqrt(vel.x * vel.x + vel.y * vel.y);
        if (vh > 0.0f) {
          const float f = m[MT_MUK] * normal / vh;
          fric = {-f * vel.x, -f * vel.y, 0.0f};
          force = force + fric;
        }
      }
    } else {
      stat = false;
    }
    mom = mom + dt * force;
    V3<float> delta = (dt * minv) * mom;
    const bool touching = rb.floor && pen >= 0.0f;
    if (touching) {
      const float work = fric.x * delta.x + fric.y * delta.y;
      const float hke = 0.5f * (mom.x * mom.x + mom.y * mom.y) * minv;
      if (hke + work <= 0.0f) stat = true;
      if (stat) mom.x = mom.y = delta.x = delta.y = 0.0f;
    } else {
      stat = false;
    }
    pos = pos + delta;
    amom = amom + dt * moment;
    q = renormalise(qmul(from_rotation_vector((dt * iinv) * amom), q));
    flags = (flags & ~(FLAG_STATIC | FLAG_CONTACT)) | (stat ? FLAG_STATIC : 0) | (touching ? FLAG_CONTACT : 0);
  }
  const float norm1 = std::fabs(pos.x) + std::fabs(pos.y) + std::fabs(pos.z) + std::fabs(amom.x) + std::fabs(amom.y) +
                      std::fabs(amom.z);
  uint32_t bits;
  std::memcpy(&bits, &norm1, 4);
  set3(s.vr, row + VR_POS, pos);
  set3(s.vr, row + VR_MOM, mom);
  s.vr[row + VR_ORI] = q.w;
  set3(s.vr, row + VR_ORI + 1, V3<float>{q.x, q.y, q.z});
  set3(s.vr, row + VR_AMOM, amom);
  const float Lm = m[MT_L];
  V3<float> area = {Lm * Lm, Lm * Lm, Lm * Lm}, ssum = {0.0f, 0.0f, 0.0f};
  if (m[MT_NU] != 0.0f) {
    area = {Lm * Lm * (1.0f + ps.y) * (1.0f + ps.z), Lm * Lm * (1.0f + ps.x) * (1.0f + ps.z),
            Lm * Lm * (1.0f + ps.x) * (1.0f + ps.y)};
    ssum = {ps.y + ps.z, ps.x + ps.z, ps.x + ps.y};
  }
  set3(s.vr, row + VR_TAREA, area);
  set3(s.vr, row + VR_TSUM, ssum);
  s.vi[v * VI_W + VI_FLAGS] = flags;
  // the rest size for the next step's links: L·(1 + T·CTE), T = T_base + A·sin(2π(τ/period + φ))
  const float temp = s.vr[row + VR_TBASE] + rb.temp_amp * wave(rb, s.vr[row + VR_CMD], s.vr[row + VR_CMD0],
                                                              rb.sin * m[MT_COSPHI] + rb.cos * m[MT_SINPHI]);
  s.vr[row + VR_SIZE] = Lm * (1.0f + temp * m[MT_CTE]);
  if (rb.events) {
    if (rb.events & EV_SAMPLE) set3(s.vr, row + VR_PSAMP, pos);
    if (rb.events & EV_START) {
      set3(s.vr, row + VR_PSTART, pos);
      set3(s.vr, row + VR_PCS, get3(s.vr, row + VR_PSAMP));
    }
    if (rb.events & EV_END) {
      set3(s.vr, row + VR_PEND, pos);
      set3(s.vr, row + VR_PCE, get3(s.vr, row + VR_PSAMP));
    }
  }
  return (bits & 0x7F800000u) == 0x7F800000u;
}

// ---- a group of links at once ----

// The host's gather instruction (AVX2's vgatherdps: one instruction where lane-by-lane loads take a load and an
// insert per lane; -DNATIVE_GATHER=0 builds those instead, for hosts whose gathers are microcoded), else a loop.
#ifndef NATIVE_GATHER
#define NATIVE_GATHER 1
#endif
inline vf gather(const float* base, vi at) {
#if defined(ISA_AVX512)
  return (vf)_mm512_i32gather_ps((__m512i)at, base, 4);
#elif defined(ISA_AVX2) && NATIVE_GATHER
  return (vf)_mm256_i32gather_ps(base, (__m256i)at, 4);
#else
  vf r;
  for (int i = 0; i < LANES; ++i) r[i] = base[at[i]];
  return r;
#endif
}
inline vi gather(const int32_t* base, vi at) {
#if defined(ISA_AVX512)
  return (vi)_mm512_i32gather_epi32((__m512i)at, base, 4);
#elif defined(ISA_AVX2) && NATIVE_GATHER
  return (vi)_mm256_i32gather_epi32(base, (__m256i)at, 4);
#else
  vi r;
  for (int i = 0; i < LANES; ++i) r[i] = base[at[i]];
  return r;
#endif
}
inline vf load(const float* p) { vf r; std::memcpy(&r, p, sizeof r); return r; }
inline vi load(const int32_t* p) { vi r; std::memcpy(&r, p, sizeof r); return r; }
inline void store(float* p, vf v) { std::memcpy(p, &v, sizeof v); }
inline void store(int32_t* p, vi v) { std::memcpy(p, &v, sizeof v); }

// The lanes 0 … count−1 of a group (a robot's last group may be short).
inline vi first_lanes(int count) {
  vi lane;
  for (int i = 0; i < LANES; ++i) lane[i] = i;
  return lane < count;
}
// a lane's int where it is active, else lane 0's (so that every index a short group gathers with is a valid one)
inline vi or_first(vi active, vi x) { return sel(active, x, vi{} + x[0]); }
// a mask's lanes as the bits of an int (lane i: bit i)
inline unsigned lane_bits(vi m) {
#if defined(ISA_AVX512)
  return _mm512_test_epi32_mask((__m512i)m, (__m512i)m);
#elif defined(ISA_AVX2)
  return unsigned(_mm256_movemask_ps((__m256)m));
#else
  unsigned r = 0;
  for (int i = 0; i < LANES; ++i) r |= unsigned(m[i] != 0) << i;
  return r;
#endif
}
// whether every lane of a mask is set
inline bool all(vi m) {
#if defined(ISA_AVX2)
  return _mm256_movemask_ps((__m256)m) == 0xFF;
#else
  int r = -1;
  for (int i = 0; i < LANES; ++i) r &= m[i];
  return r != 0;
#endif
}
// the lanes `on` of v into p … p+LANES−1 (a masked store: the lanes beyond a short group belong to the next robot,
// which another thread may be writing)
inline void store_on(float* p, vf v, vi on) {
#if defined(ISA_AVX512)
  _mm512_mask_storeu_ps(p, _mm512_cmpneq_epi32_mask((__m512i)on, _mm512_setzero_si512()), (__m512)v);
#elif defined(ISA_AVX2)  // (a plain store where every lane is on: a masked store costs more, on AMD's cores most)
  if (all(on)) _mm256_storeu_ps(p, (__m256)v);
  else _mm256_maskstore_ps(p, (__m256i)on, (__m256)v);
#else
  for (int i = 0; i < LANES; ++i)
    if (on[i]) p[i] = v[i];
#endif
}
inline void store_on(int32_t* p, vi v, vi on) {
#if defined(ISA_AVX512)
  _mm512_mask_storeu_epi32(p, _mm512_cmpneq_epi32_mask((__m512i)on, _mm512_setzero_si512()), (__m512i)v);
#elif defined(ISA_AVX2)
  if (all(on)) _mm256_storeu_si256((__m256i*)p, (__m256i)v);
  else _mm256_maskstore_epi32(p, (__m256i)on, (__m256i)v);
#else
  for (int i = 0; i < LANES; ++i)
    if (on[i]) p[i] = v[i];
#endif
}
// whether any lane of a mask is set
inline bool any(vi m) {
#if defined(ISA_AVX512)
  return _mm512_test_epi32_mask((__m512i)m, (__m512i)m) != 0;
#elif defined(ISA_AVX2)
  return !_mm256_testz_si256((__m256i)m, (__m256i)m);
#else
  int r = 0;
  for (int i = 0; i < LANES; ++i) r |= m[i];
  return r != 0;
#endif
}

// Links lk … lk+count−1 (count ≤ LANES) along the common path; returns the lanes off it (a large-angle link, a regime
// switch into the large angle, an end rotation beyond atan's series), whose state it leaves as it was, and sets
// `diverged`.
inline vi link_group(const Regions& s, int lk, int count, float prev_dt, float max_strain, int& diverged) {
  const int L = s.links;
  const vi active = first_lanes(count);
  const vi n = or_first(active, load(s.li + lk + LI_NEG * L)), p = or_first(active, load(s.li + lk + LI_POS * L));
  const vi axis = or_first(active, load(s.li + lk + LI_AXIS * L)), flags = load(s.li + lk + LI_FLAGS * L);
  const vi vn = n * VR_W, vp = p * VR_W, lt = or_first(active, load(s.li + lk + LI_LMAT * L)) * LT_W;
  const vi ay = axis == 1, az = axis == 2;
  const vi small0 = (flags & FLAG_SMALL) != 0, valid0 = (flags & FLAG_VALID) != 0;
  const vf L0 = 0.5f * (gather(s.vr, vn + VR_SIZE) + gather(s.vr, vp + VR_SIZE));
  const Q4<vf> qn = {gather(s.vr, vn + VR_ORI), gather(s.vr, vn + VR_ORI + 1), gather(s.vr, vn + VR_ORI + 2),
                     gather(s.vr, vn + VR_ORI + 3)};
  const Q4<vf> qp = {gather(s.vr, vp + VR_ORI), gather(s.vr, vp + VR_ORI + 1), gather(s.vr, vp + VR_ORI + 2),
                     gather(s.vr, vp + VR_ORI + 3)};
  const V3<vf> d = {gather(s.vr, vp + VR_POS) - gather(s.vr, vn + VR_POS),
                    gather(s.vr, vp + VR_POS + 1) - gather(s.vr, vn + VR_POS + 1),
                    gather(s.vr, vp + VR_POS + 2) - gather(s.vr, vn + VR_POS + 2)};
  // 1. orientLink
  const Q4<vf> R = conj(q_to_axis_x(qn, ay, az));
  V3<vf> pos2 = rotate(R, to_axis_x(d, ay, az));
  const Q4<vf> q2 = qmul(R, q_to_axis_x(qp, ay, az));
  const vf area = 0.5f * (gather(s.vr, vn + VR_TAREA + axis) + gather(s.vr, vp + VR_TAREA + axis));
  const vf ssum = 0.5f * (gather(s.vr, vn + VR_TSUM + axis) + gather(s.vr, vp + VR_TSUM + axis));
  const vf small_turn = (fabs_(pos2.z) + fabs_(pos2.y)) / pos2.x, extend = fabs_(1.0f - pos2.x / L0);
  const vi leave = small0 & ((small_turn > HYST * SA_BEND) | (extend > HYST * SA_EXT));
  const vi enter = ~small0 & (small_turn < SA_BEND) & (extend < SA_EXT);
  const vi small = enter | (small0 & ~leave), valid = valid0 & ~enter & ~leave;
  const vi off = ~(small & series_applies(q2)) & active, on = ~off & active;
  // the small angle: p.x −= L0, the offsets act as shear, q1 the identity (a1v = 0)
  pos2.x = pos2.x - L0;
  const V3<vf> a2v = rotation_vector_series(q2);
  const vf strain = pos2.x / L0;
  // 2. half the change since the last step (a1v = 0)
  const V3<vf> P2o = {load(s.lr + lk + LR_P2 * L), load(s.lr + lk + (LR_P2 + 1) * L), load(s.lr + lk + (LR_P2 + 2) * L)};
  const V3<vf> A1o = {load(s.lr + lk + LR_A1 * L), load(s.lr + lk + (LR_A1 + 1) * L), load(s.lr + lk + (LR_A1 + 2) * L)};
  const V3<vf> A2o = {load(s.lr + lk + LR_A2 * L), load(s.lr + lk + (LR_A2 + 1) * L), load(s.lr + lk + (LR_A2 + 2) * L)};
  const V3<vf> dP = 0.5f * (pos2 - P2o), dA1 = -0.5f * A1o, dA2 = 0.5f * (a2v - A2o);
  // 3.-4. stress
  const vf nu = gather(s.lt, lt + LT_NU);
  const vf stress = sel(nu != 0.0f, gather(s.lt, lt + LT_EHAT) * ((1.0f - nu) * strain + nu * ssum),
                        gather(s.lt, lt + LT_E) * strain);
  // 5. elastic loads (a1v = 0)
  const vf b1 = gather(s.lt, lt + LT_B1), b2 = gather(s.lt, lt + LT_B2), b3 = gather(s.lt, lt + LT_B3),
           a2 = gather(s.lt, lt + LT_A2);
  V3<vf> fN = {stress * area, b1 * pos2.y - b2 * a2v.z, b1 * pos2.z + b2 * a2v.y};
  V3<vf> fP = neg(fN);
  V3<vf> mN = {a2 * a2v.x, -b2 * pos2.z - b3 * a2v.y, b2 * pos2.y - b3 * a2v.z};
  V3<vf> mP = {-a2 * a2v.x, -b2 * pos2.z - b3 * (2.0f * a2v.y), b2 * pos2.y - b3 * (2.0f * a2v.z)};
  // 6. internal damping where the rates are valid
  const vf zero = {};
  const vf dN = sel(valid, gather(s.mt, gather(s.vi, n * VI_W + VI_MAT) * MT_W + MT_DAMP) / prev_dt, zero);
  const vf dPp = sel(valid, gather(s.mt, gather(s.vi, p * VI_W + VI_MAT) * MT_W + MT_DAMP) / prev_dt, zero);
  const vf sqA1 = gather(s.lt, lt + LT_SQA1), sqA2xIp = gather(s.lt, lt + LT_SQA2XIP), sqB1 = gather(s.lt, lt + LT_SQB1),
           sqB2xFMp = gather(s.lt, lt + LT_SQB2XFMP), sqB3xIp = gather(s.lt, lt + LT_SQB3XIP);
  const V3<vf> c = {sqA1 * dP.x, sqB1 * dP.y - sqB2xFMp * (dA1.z + dA2.z), sqB1 * dP.z + sqB2xFMp * (dA1.y + dA2.y)};
  fN = fN + dN * c;
  fP = fP - dPp * c;
  mN = mN - (0.5f * dN) * V3<vf>{-sqA2xIp * (dA2.x - dA1.x), sqB2xFMp * dP.z + sqB3xIp * (2.0f * dA1.y + dA2.y),
                                 -sqB2xFMp * dP.y + sqB3xIp * (2.0f * dA1.z + dA2.z)};
  mP = mP - (0.5f * dPp) * V3<vf>{sqA2xIp * (dA2.x - dA1.x), sqB2xFMp * dP.z + sqB3xIp * (dA1.y + 2.0f * dA2.y),
                                  -sqB2xFMp * dP.y + sqB3xIp * (dA1.z + 2.0f * dA2.z)};
  // 7. the positive end's loads into its voxel frame (the negative end's frame is the link's at a small angle)
  fP = rotate(conj(q2), fP);
  mP = rotate(conj(q2), mP);
  // the lanes on the path take the new state, the others keep theirs for link_update
  const V3<vf> out[7] = {to_axis_original(fN, ay, az), to_axis_original(fP, ay, az), to_axis_original(mN, ay, az),
                         to_axis_original(mP, ay, az), pos2, V3<vf>{zero, zero, zero}, a2v};
  const int col[7] = {LR_FN, LR_FP, LR_MN, LR_MP, LR_P2, LR_A1, LR_A2};
  for (int j = 0; j < 7; ++j)
    for (int k = 0; k < 3; ++k) {
      float* at = s.lr + lk + (col[j] + k) * L;
      store_on(at, k == 0 ? out[j].x : (k == 1 ? out[j].y : out[j].z), on);
    }
  store_on(s.lr + lk + LR_STRAIN * L, strain, on);
  store_on(s.li + lk + LI_FLAGS * L, vi{} + (FLAG_SMALL | FLAG_VALID), on);
  // 8. divergence on the path's lanes (NaN and inf by the exponent bits, as link_update)
  const vi bad = on & ((strain > max_strain) | (((vi)strain & 0x7F800000) == 0x7F800000));
  diverged |= any(bad);
  return off;
}

// v's lanes `on` into base[at[i]], where lane i's index is lane 0's + i·W (a group's consecutive rows of width W:
// the lanes `on` are among them): AVX-512's scatter; elsewhere (AVX2 has no scatter) lane by lane at fixed offsets
// from lane 0's, and without a test per lane when every lane is on (as good as always).
template <int W, class T, class TV> inline void scatter_rows(T* base, vi at, TV v, vi on) {
#if defined(ISA_AVX512)
  const __mmask16 k = _mm512_cmpneq_epi32_mask((__m512i)on, _mm512_setzero_si512());
  if constexpr (std::is_floating_point_v<T>) _mm512_mask_i32scatter_ps(base, k, (__m512i)at, (__m512)v, 4);
  else _mm512_mask_i32scatter_epi32(base, k, (__m512i)at, (__m512i)v, 4);
#else
  T* p = base + at[0];
  if (all(on)) {
    for (int i = 0; i < LANES; ++i) p[i * W] = v[i];
  } else {
    for (int i = 0; i < LANES; ++i)
      if (on[i]) p[i * W] = v[i];
  }
#endif
}
inline vf vsqrt(vf x) {
#if defined(ISA_AVX512)
  return (vf)_mm512_sqrt_ps((__m512)x);
#elif defined(ISA_AVX2)
  return (vf)_mm256_sqrt_ps((__m256)x);
#else
  vf r;
  for (int i = 0; i < LANES; ++i) r[i] = std::sqrt(x[i]);
  return r;
#endif
}
// cos, sin and pow lane by lane, in loops g++ hands to glibc's vector maths (libmvec) under -ffast-math
inline vf vcos(vf x) {
  float a[LANES], r[LANES];
  std::memcpy(a, &x, sizeof a);
#pragma omp simd
  for (int i = 0; i < LANES; ++i) r[i] = std::cos(a[i]);
  std::memcpy(&x, r, sizeof r);
  return x;
}
inline vf vsin(vf x) {
  float a[LANES], r[LANES];
  std::memcpy(a, &x, sizeof a);
#pragma omp simd
  for (int i = 0; i < LANES; ++i) r[i] = std::sin(a[i]);
  std::memcpy(&x, r, sizeof r);
  return x;
}
inline vf vpow(vf x, vf y) {
  float a[LANES], b[LANES], r[LANES];
  std::memcpy(a, &x, sizeof a);
  std::memcpy(b, &y, sizeof b);
#pragma omp simd
  for (int i = 0; i < LANES; ++i) r[i] = std::pow(a[i], b[i]);
  std::memcpy(&x, r, sizeof r);
  return x;
}
template <class F> inline V3<F> gather3(const float* base, vi at) {
  return {gather(base, at), gather(base, at + 1), gather(base, at + 2)};
}
inline void scatter3(float* base, vi at, V3<vf> v, vi on) {
  scatter_rows<VR_W>(base, at, v.x, on);
  scatter_rows<VR_W>(base, at + 1, v.y, on);
  scatter_rows<VR_W>(base, at + 2, v.z, on);
}

// Voxels v … v+count−1 (count ≤ LANES) of one robot along the common path; returns the lanes off it, whose state it
// leaves as it was, and sets `diverged`.
inline vi voxel_group(const Regions& s, int v0, int count, const Robot& rb, int& diverged) {
  const int L = s.links;
  const vf zero = {}, one = zero + 1.0f;
  const vi active = first_lanes(count);
  vi v;
  for (int i = 0; i < LANES; ++i) v[i] = v0 + (i < count ? i : 0);
  const vi row = v * VR_W, irow = v * VI_W;
  const vi mat = gather(s.vi, irow + VI_MAT), flags = gather(s.vi, irow + VI_FLAGS), m = mat * MT_W;
  const vf minv = gather(s.mt, m + MT_MINV), iinv = gather(s.mt, m + MT_IINV), dt = zero + rb.dt;
  V3<vf> pos = gather3<vf>(s.vr, row + VR_POS), mom = gather3<vf>(s.vr, row + VR_MOM),
         amom = gather3<vf>(s.vr, row + VR_AMOM);
  Q4<vf> q = {gather(s.vr, row + VR_ORI), gather(s.vr, row + VR_ORI + 1), gather(s.vr, row + VR_ORI + 2),
              gather(s.vr, row + VR_ORI + 3)};
  const vf size = gather(s.vr, row + VR_SIZE), nu = gather(s.mt, m + MT_NU);
  vi off = (flags & FLAG_FIXED) != 0;
  if (rb.events) off = off | (vi{} - 1);
  // Poisson strain, and the link loads, through the six slots
  vf strain[3], add = zero;
  vi tension[3];
  V3<vf> force = {zero, zero, zero}, moment = {zero, zero, zero};
  for (int a = 0; a < 3; ++a) {
    strain[a] = zero;
    vi cnt = vi{};
    for (int side = 0; side < 2; ++side) {
      const vi lk = gather(s.vi, irow + VI_SLOT + 2 * a + side), has = lk >= 0, at = sel(has, lk, vi{});
      const vf eps = gather(s.lr + LR_STRAIN * L, at);
      // (a lane without a link reads link 0's columns, another robot's, maybe never copied in this call: its
      // material is taken as 0, a valid index, and what it reads is discarded)
      const vi lmat = sel(has, gather(s.li + LI_LMAT * L, at), vi{});
      const vf coef = gather(s.lt, lmat * LT_W + (side == 1 ? LT_PSPOS : LT_PSNEG));
      strain[a] += sel(has, eps * coef, zero);
      cnt -= has;
      const int f = side == 1 ? LR_FP : LR_FN, mm = side == 1 ? LR_MP : LR_MN;
      force = force + V3<vf>{sel(has, gather(s.lr + f * L, at), zero), sel(has, gather(s.lr + (f + 1) * L, at), zero),
                             sel(has, gather(s.lr + (f + 2) * L, at), zero)};
      moment = moment + V3<vf>{sel(has, gather(s.lr + mm * L, at), zero),
                               sel(has, gather(s.lr + (mm + 1) * L, at), zero),
                               sel(has, gather(s.lr + (mm + 2) * L, at), zero)};
    }
    tension[a] = cnt == 2;
    strain[a] = sel(tension[a], 0.5f * strain[a], strain[a]);
    add += sel(tension[a], strain[a], zero);
  }
  const vi all_tension = tension[0] & tension[1] & tension[2];
  vf c = gather(s.mt, m + MT_PB1 + POISSON_SERIES_TERMS - 1);
  for (int k = POISSON_SERIES_TERMS - 1; k > 0; --k) c = gather(s.mt, m + MT_PB1 + k - 1) + add * c;
  vf val = add * c;
  const vi powed = ~all_tension & (fabs_(add) >= POISSON_SERIES_X) & (nu != 0.0f);  // (beyond the series: powf)
  if (any(powed)) val = sel(powed, vpow(1.0f + add, -nu) - 1.0f, val);
  V3<vf> ps;
  ps.x = sel(nu != 0.0f, sel(tension[0], strain[0], val), zero);
  ps.y = sel(nu != 0.0f, sel(tension[1], strain[1], val), zero);
  ps.z = sel(nu != 0.0f, sel(tension[2], strain[2], val), zero);
  // forces, the flat floor, the update
  const V3<vf> vel = minv * mom;
  force = rotate(q, force) - gather(s.mt, m + MT_CG) * vel;
  force.z += gather(s.mt, m + MT_MG);
  moment = rotate(q, moment) - gather(s.mt, m + MT_CGR) * (iinv * amom);
  const vi static0 = (flags & FLAG_STATIC) != 0;
  const vf pen = 0.5f * size - 0.5f * gather(s.mt, m + MT_L) - pos.z;
  const vi contact = (pen >= 0.0f) & (vi{} - rb.floor);
  const vf normal = gather(s.mt, m + MT_KPEN) * pen;
  force.z += sel(contact, normal - gather(s.mt, m + MT_CC) * vel.z, zero);
  const vf mus = gather(s.mt, m + MT_MUS) * normal;
  vi stat = contact & static0 & ~(force.x * force.x + force.y * force.y > mus * mus);
  const vf vh = vsqrt(vel.x * vel.x + vel.y * vel.y);
  const vi kinetic = contact & ~static0 & (vh > 0.0f);
  const vf f = sel(kinetic, gather(s.mt, m + MT_MUK) * normal / sel(kinetic, vh, one), zero);
  const V3<vf> fric = {-f * vel.x, -f * vel.y, zero};
  force.x += fric.x;
  force.y += fric.y;
  mom = mom + dt * force;
  V3<vf> delta = (dt * minv) * mom;
  const vf work = fric.x * delta.x + fric.y * delta.y, hke = 0.5f * (mom.x * mom.x + mom.y * mom.y) * minv;
  stat = contact & (stat | (hke + work <= 0.0f));
  mom.x = sel(stat, zero, mom.x);
  mom.y = sel(stat, zero, mom.y);
  delta.x = sel(stat, zero, delta.x);
  delta.y = sel(stat, zero, delta.y);
  pos = pos + delta;
  amom = amom + dt * moment;
  const V3<vf> th = 0.5f * ((dt * iinv) * amom);
  const vf a2 = th.x * th.x + th.y * th.y + th.z * th.z;
  vf w = 1.0f - a2 / 2.0f, k = 1.0f - a2 / 6.0f;  // (FromRotationVector's Taylor form, and cos, sin beyond it)
  const vi turned = a2 * a2 >= ROTVEC_SMALL4;
  if (any(turned)) {
    const vf a = vsqrt(a2);
    w = sel(turned, vcos(a), w);
    k = sel(turned, vsin(a) / sel(turned, a, one), k);
  }
  q = qmul(Q4<vf>{w, th.x * k, th.y * k, th.z * k}, q);
  const vf n2 = q.w * q.w + q.x * q.x + q.y * q.y + q.z * q.z;
  const vf kq = sel(fabs_(n2 - 1.0f) < RENORM_NEWTON, 1.5f - 0.5f * n2, 1.0f / vsqrt(n2));
  q = {q.w * kq, q.x * kq, q.y * kq, q.z * kq};
  const vi new_flags = (flags & ~(FLAG_STATIC | FLAG_CONTACT)) | (stat & FLAG_STATIC) | (contact & FLAG_CONTACT);
  // store the lanes on the path
  off = off & active;
  const vi on = ~off & active;
  const vf norm1 = fabs_(pos.x) + fabs_(pos.y) + fabs_(pos.z) + fabs_(amom.x) + fabs_(amom.y) + fabs_(amom.z);
  const vi bad = on & (((vi)norm1 & 0x7F800000) == 0x7F800000);
  diverged |= any(bad);
  scatter3(s.vr, row + VR_POS, pos, on);
  scatter3(s.vr, row + VR_MOM, mom, on);
  scatter_rows<VR_W>(s.vr, row + VR_ORI, q.w, on);
  scatter3(s.vr, row + VR_ORI + 1, V3<vf>{q.x, q.y, q.z}, on);
  scatter3(s.vr, row + VR_AMOM, amom, on);
  const vf Lm = gather(s.mt, m + MT_L), L2 = Lm * Lm;
  const vi poisson = nu != 0.0f;
  scatter3(s.vr, row + VR_TAREA, V3<vf>{sel(poisson, L2 * (1.0f + ps.y) * (1.0f + ps.z), L2),
                                        sel(poisson, L2 * (1.0f + ps.x) * (1.0f + ps.z), L2),
                                        sel(poisson, L2 * (1.0f + ps.x) * (1.0f + ps.y), L2)}, on);
  scatter3(s.vr, row + VR_TSUM, V3<vf>{sel(poisson, ps.y + ps.z, zero), sel(poisson, ps.x + ps.z, zero),
                                       sel(poisson, ps.x + ps.y, zero)}, on);
  scatter_rows<VI_W>(s.vi, irow + VI_FLAGS, new_flags, on);
  const vf temp = gather(s.vr, row + VR_TBASE) +
                  rb.temp_amp * wave(rb, gather(s.vr, row + VR_CMD), gather(s.vr, row + VR_CMD0),
                                     rb.sin * gather(s.mt, m + MT_COSPHI) + rb.cos * gather(s.mt, m + MT_SINPHI));
  scatter_rows<VR_W>(s.vr, row + VR_SIZE, Lm * (1.0f + temp * gather(s.mt, m + MT_CTE)), on);
  return off;
}

// A group of up to LANES links from lk (to `end`) at once, the lanes off the common path by link_update; returns how
// many those were.
inline int links_at_once(const Regions& s, int lk, int end, float prev_dt, float max_strain, int& diverged) {
  const int count = end - lk < LANES ? end - lk : LANES;
  const vi off = link_group(s, lk, count, prev_dt, max_strain, diverged);
  int slow = 0;
  for (unsigned lanes = lane_bits(off); lanes; lanes &= lanes - 1, ++slow) {  // (each lane off, lowest first)
    const int i = __builtin_ctz(lanes);
    diverged |= link_update(s, lk + i, prev_dt, max_strain);
  }
  return slow;
}
inline int voxels_at_once(const Regions& s, int v, int end, const Robot& rb, int& diverged) {
  const int count = end - v < LANES ? end - v : LANES;
  const vi off = voxel_group(s, v, count, rb, diverged);
  int slow = 0;
  for (unsigned lanes = lane_bits(off); lanes; lanes &= lanes - 1, ++slow) {  // (each lane off, lowest first)
    const int i = __builtin_ctz(lanes);
    diverged |= voxel_update(s, v + i, rb);
  }
  return slow;
}

// Workers kept between calls (a control period of one step is a call: starting threads per call cost as much as
// the step), woken for each call's robots. Calls are serialised (one pool per process: this_process_pool).
class Pool {
 public:
  // fn() on `threads` threads at once, this one among them; returns when all have returned
  void run(int threads, const std::function<void()>& fn) {
    std::lock_guard<std::mutex> one_call(call_);
    std::unique_lock<std::mutex> lock(m_);
    while (int(workers_.size()) < threads - 1) {
      const int id = int(workers_.size());
      workers_.emplace_back([this, id] { serve(id); });
    }
    job_ = &fn;
    wanted_ = pending_ = threads - 1;
    ++generation_;
    lock.unlock();
    wake_.notify_all();
    fn();
    lock.lock();
    done_.wait(lock, [&] { return pending_ == 0; });
  }
 private:
  void serve(int id) {
    long seen = 0;
    std::unique_lock<std::mutex> lock(m_);
    for (;;) {
      wake_.wait(lock, [&] { return generation_ != seen; });
      seen = generation_;
      if (id >= wanted_) continue;  // (this call wants fewer threads)
      const std::function<void()>* job = job_;
      lock.unlock();
      (*job)();
      lock.lock();
      if (--pending_ == 0) done_.notify_one();
    }
  }
  std::mutex call_, m_;
  std::condition_variable wake_, done_;
  std::vector<std::thread> workers_;
  const std::function<void()>* job_ = nullptr;
  long generation_ = 0;
  int wanted_ = 0, pending_ = 0;
};

// This process's pool, never destroyed (its idle workers end with the process). A process forked from one that
// had a pool gets a new one: the copy's workers are not there (the old one is left untouched).
Pool& this_process_pool() {
  static Pool* pool = nullptr;
  static pid_t owner = 0;
  if (pool == nullptr || owner != getpid()) {
    pool = new Pool;
    owner = getpid();
  }
  return *pool;
}

// fn(r) for every robot r, `threads` workers taking the next robot in turn (robots are independent; the pool's
// threads, not an OpenMP runtime beside torch's); the sum of what fn returned.
template <class Fn> long for_each_robot(int robots, int threads, Fn fn) {
  std::atomic<int> next{0};
  std::atomic<long> total{0};
  const std::function<void()> work = [&] {
    long sum = 0;
    for (int r; (r = next.fetch_add(1)) < robots;) sum += fn(r);
    total += sum;
  };
  this_process_pool().run(std::max(1, std::min(threads, robots)), work);
  return total;
}

// ---- the robot phase (clock.py:robot_advance with a fixed dt; schedules.py:trace_sample) ----

struct Batch {  // the buffers' regions as the robot phase reads them
  const int32_t* h;
  int32_t* ri;
  double *rt, *tr;
  const double* gp;
  int floor, command;
};

// What robot r's voxels read of it this step (voxels.py:temperature's ramp, in its f64 clock arithmetic).
inline Robot robot_now(const Batch& b, int r) {
  const double* rt = b.rt + r * RT_W;
  Robot rb{float(rt[RT_DT]), float(rt[RT_SIN]), float(rt[RT_COS]), float(b.gp[GP_TEMP_AMP]), b.ri[r * RI_W + RI_EVENTS],
           b.floor, b.command, 0, 1.0f};
  if (b.command != 0 && rt[RT_RAMP] > 0.0 && rt[RT_UNTIL] < NO_LIMIT) {
    const double frac = 1.0 - (rt[RT_UNTIL] - (rt[RT_T] + rt[RT_DT])) / rt[RT_RAMP];  // (t + dt: Voxelyze's time)
    if (frac < 1.0) {
      rb.ramping = 1;
      rb.blend = float(frac > 0.0 ? frac : 0.0);
    }
  }
  return rb;
}

// The trace's frame f of robot r (summaries.py:summarise_robot), its sums in f64 in the voxels' order.
inline void summarise_robot(const Regions& s, const Batch& b, int r, int f) {
  const int v0 = b.ri[r * RI_W + RI_VSTART], v1 = b.ri[r * RI_W + RI_VEND];
  double mx[3] = {0.0, 0.0, 0.0}, lo[3], hi[3], q[4] = {0.0, 0.0, 0.0, 0.0}, m = 0.0;
  int contacts = 0;
  for (int k = 0; k < 3; ++k) lo[k] = hi[k] = double(s.vr[v0 * VR_W + VR_POS + k]);
  for (int v = v0; v < v1; ++v) {
    const double mass = double(s.mt[s.vi[v * VI_W + VI_MAT] * MT_W + MT_MASS]);
    for (int k = 0; k < 3; ++k) {
      const double p = double(s.vr[v * VR_W + VR_POS + k]);
      mx[k] += mass * p;
      lo[k] = p < lo[k] ? p : lo[k];
      hi[k] = p > hi[k] ? p : hi[k];
    }
    m += mass;
    if (s.vi[v * VI_W + VI_FLAGS] & FLAG_CONTACT) ++contacts;
    const double sign = s.vr[v * VR_W + VR_ORI] < 0.0f ? -1.0 : 1.0;
    for (int k = 0; k < 4; ++k) q[k] += sign * double(s.vr[v * VR_W + VR_ORI + k]);
  }
  const int stride = b.h[HDR_TR_STRIDE];
  auto put = [&](int c, double x) { b.tr[(f * SUMMARY_W + c) * stride + r] = x; };
  put(SUMMARY_T, b.rt[r * RT_W + RT_T]);
  put(SUMMARY_STATUS, double(b.ri[r * RI_W + RI_STATUS]));
  put(SUMMARY_M, m);
  put(SUMMARY_CONTACTS, double(contacts));
  for (int k = 0; k < 3; ++k) {
    put(SUMMARY_MX + k, mx[k]);
    put(SUMMARY_LO + k, lo[k]);
    put(SUMMARY_HI + k, hi[k]);
  }
  for (int k = 0; k < 4; ++k) put(SUMMARY_Q + k, q[k]);
}

// The end of robot r's step: its clock, status, the next step's actuation phase and snapshots, the trace.
inline void robot_advance(const Regions& s, const Batch& b, int r) {
  double* rt = b.rt + r * RT_W;
  int32_t* ri = b.ri + r * RI_W;
  rt[RT_DTPREV] = rt[RT_DT];
  rt[RT_T] = rt[RT_T] + rt[RT_DT];
  const int step = ri[RI_STEP] + 1;
  ri[RI_STEP] = step;
  if (rt[RT_T] > b.gp[GP_T_END] && ri[RI_STATUS] == STATUS_RUNNING) ri[RI_STATUS] = STATUS_DONE;
  if (step >= ri[RI_MAXSTEP] && ri[RI_STATUS] == STATUS_RUNNING) ri[RI_STATUS] = STATUS_STALLED;
  const double a = TWO_PI * (rt[RT_T] + rt[RT_DT]) / b.gp[GP_TEMP_PERIOD];
  rt[RT_SIN] = std::sin(a);
  rt[RT_COS] = std::cos(a);
  const double t_before = rt[RT_T], t_after = t_before + rt[RT_DT];
  int events = 0;
  if ((step + 1) % ri[RI_PERIOD] == 0) events |= EV_SAMPLE;
  if (t_before <= b.gp[GP_BURN_IN] && t_after > b.gp[GP_BURN_IN]) events |= EV_START;
  if (t_before <= b.gp[GP_T_END] && t_after > b.gp[GP_T_END]) events |= EV_END;
  ri[RI_EVENTS] = events;
  const int every = b.h[HDR_TRACE_STEPS];
  if (every > 0 && step % every == 0 && step / every < b.h[HDR_TRACE_FRAMES]) summarise_robot(s, b, r, step / every);
}

// The link tables column by column (this code's layout: LANES consecutive links' column is one vector load), kept
// between calls (grown, never shrunk: nothing allocated per control period). Each robot's links are copied in
// before its first step of a call (what the link phase reads: the last pose, rotation vectors, the ints) and back
// after its last (what it writes: every column but OMEGA2, the flags), by the thread that steps it: in its cache,
// on every thread at once, and not at all for a robot that does not step.
struct Columns {
  std::vector<float> lr;
  std::vector<int32_t> li;
  void fit(int links) {  // (+ a group: a short group's full-width loads)
    if (lr.size() < size_t(links) * LR_W + LANES) lr.resize(size_t(links) * LR_W + LANES);
    if (li.size() < size_t(links) * LI_W + LANES) li.resize(size_t(links) * LI_W + LANES);
  }
};
constexpr int LR_READ = LR_A2 + 3, LR_WRITTEN = LR_MP + 3;  // (P2, A1, A2 first; OMEGA2, rl4design's, last)
static_assert(LR_P2 == 0 && LR_A1 == 3 && LR_A2 == 6 && LR_OMEGA2 == LR_W - 1, "the link columns' order");

struct LinkRows {  // the engine's link tables, row by row
  float* lr;
  int32_t* li;
};
inline void links_in(const Regions& s, const LinkRows& rows, int l0, int l1) {
  const int L = s.links;
  for (int lk = l0; lk < l1; ++lk) {
    for (int c = 0; c < LR_READ; ++c) s.lr[c * L + lk] = rows.lr[lk * LR_W + c];
    for (int c = 0; c < LI_W; ++c) s.li[c * L + lk] = rows.li[lk * LI_W + c];
  }
}
inline void links_out(const Regions& s, const LinkRows& rows, int l0, int l1) {
  const int L = s.links;
  for (int lk = l0; lk < l1; ++lk) {
    for (int c = 0; c < LR_WRITTEN; ++c) rows.lr[lk * LR_W + c] = s.lr[c * L + lk];
    rows.li[lk * LI_W + LI_FLAGS] = s.li[LI_FLAGS * L + lk];
  }
}

// One step of robot r: each link, then (VOXELS) each voxel, then (CLOCK) its clock and trace — schedules.py:
// robot_steps with one lane. VECTOR: a group of lanes at once along the common path (else every item by the
// branching updates). Returns false where a link or voxel diverged (the robot is marked so); counts into `slow` the
// item-steps that went through the branching updates.
template <bool VECTOR, bool VOXELS, bool CLOCK>
inline bool robot_step(const Regions& s, const Batch& b, int r, float max_strain, long& slow) {
  int32_t* robot = b.ri + r * RI_W;
  const float prev_dt = float(b.rt[r * RT_W + RT_DTPREV]);
  int diverged = 0;
  for (int lk = robot[RI_LSTART]; lk < robot[RI_LEND]; lk += VECTOR ? LANES : 1) {
    if (VECTOR) {
      slow += links_at_once(s, lk, robot[RI_LEND], prev_dt, max_strain, diverged);
    } else {
      diverged |= link_update(s, lk, prev_dt, max_strain);
      ++slow;
    }
  }
  if (!diverged && VOXELS) {  // (a diverged link aborts the step, as in VX)
    const Robot rb = robot_now(b, r);
    for (int v = robot[RI_VSTART]; v < robot[RI_VEND]; v += VECTOR ? LANES : 1) {
      if (VECTOR) {
        slow += voxels_at_once(s, v, robot[RI_VEND], rb, diverged);
      } else {
        diverged |= voxel_update(s, v, rb);
        ++slow;
      }
    }
  }
  if (diverged) {
    robot[RI_STATUS] = STATUS_DIVERGED;
    return false;
  }
  if (CLOCK) robot_advance(s, b, r);
  return true;
}

// n_steps of every robot still stepping (running, its clock before its limit RT.UNTIL), the robots shared among
// `threads` workers (robot_step). floor, command: Switches.floor, Switches.command. Returns how many item-steps
// went through the branching updates.
template <bool VECTOR, bool VOXELS, bool CLOCK>
long run(float* reals, int32_t* ints, double* f64s, int n_steps, int threads, int floor, int command) {
  static std::mutex one_call;  // (the columns are kept between calls: Python threads calling at once take turns)
  static Columns cols;
  std::lock_guard<std::mutex> turn(one_call);
  const int32_t* h = ints;
  cols.fit(h[HDR_N_LINKS]);
  const Regions s{reals + h[HDR_VR_AT], cols.lr.data(), reals + h[HDR_MT_AT], reals + h[HDR_LT_AT], ints + h[HDR_VI_AT],
                  cols.li.data(), h[HDR_N_LINKS]};
  const LinkRows rows{reals + h[HDR_LR_AT], ints + h[HDR_LI_AT]};
  const Batch b{h, ints + h[HDR_RI_AT], f64s + h[HDR_RT_AT], f64s + h[HDR_TR_AT], f64s + h[HDR_GP_AT], floor, command};
  const float max_strain = float(b.gp[GP_MAX_STRAIN]);
  return for_each_robot(h[HDR_N_ROBOTS], threads, [&](int r) {
    long slow = 0;
    const int32_t* robot = b.ri + r * RI_W;
    const double* clock = b.rt + r * RT_W;
    int step = 0;
    for (; step < n_steps && robot[RI_STATUS] == STATUS_RUNNING && clock[RT_T] < clock[RT_UNTIL]; ++step) {
      if (step == 0) links_in(s, rows, robot[RI_LSTART], robot[RI_LEND]);
      if (!robot_step<VECTOR, VOXELS, CLOCK>(s, b, r, max_strain, slow)) {
        ++step;
        break;
      }
    }
    if (step > 0) links_out(s, rows, robot[RI_LSTART], robot[RI_LEND]);
    return slow;
  });
}

}  // namespace

// Engine.advance on the native schedule (every phase, LANES items at once).
extern "C" long advance(float* reals, int32_t* ints, double* f64s, int n_steps, int threads, int floor, int command) {
  return run<true, true, true>(reals, ints, f64s, n_steps, threads, floor, command);
}

// For the tests and scripts/profile_sim.py's segments: the link phase alone, or the link and voxel phases without
// the robot phase (the clock stands still), one item at a time or LANES at once, with the floor and the sine's
// actuation.
extern "C" long links_vector(float* reals, int32_t* ints, double* f64s, int n, int threads) {
  return run<true, false, false>(reals, ints, f64s, n, threads, 1, 0);
}
extern "C" long links_voxels_scalar(float* reals, int32_t* ints, double* f64s, int n, int threads) {
  return run<false, true, false>(reals, ints, f64s, n, threads, 1, 0);
}
extern "C" long links_voxels_vector(float* reals, int32_t* ints, double* f64s, int n, int threads) {
  return run<true, true, false>(reals, ints, f64s, n, threads, 1, 0);
}

// What this build runs a group on (native.built_for: benchmarks and profile_sim print it beside their figures).
extern "C" int lanes() { return LANES; }
extern "C" const char* instruction_set() {
#if defined(ISA_AVX512)
  return "AVX-512";
#elif defined(ISA_AVX2)
  return "AVX2";
#else
  return "generic vectors";
#endif
}
