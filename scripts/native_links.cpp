// The link update (spec section 5, Voxelyze's CVX_Link::updateForces) in C++, for scripts/probe_native_links.py:
// what the CPU simulator's link phase costs when compiled outside Taichi, one link at a time and 16 links per
// instruction (issue 43; docs/physics.md, "The link phase in C++, probed").
//
// The same arithmetic as freeform/sim/links.py and quat.py on the f32 path (Voxelyze semantics, fixed dt: no
// rl4design slips, no omega^2 store), on the engine's own packed buffers; the column indices and widths come from
// freeform/sim/state.py through the generated layout.h (the probe writes it), so this file never spells an offset.
// The link tables are read column by column (copied so on entry and back on exit: this code's own layout, which
// makes a column of 16 consecutive links one vector load); the voxel rows are gathered.
//
// link_steps_scalar: every link by `link_update`, with Voxelyze's branches.
// link_steps_vector: 16 links at once by `link_group` (GCC's vector extensions: one source of the math, templated
// on the lane type) along the common path — a small-angle link whose end rotation takes atan's series — and every
// lane off that path again by `link_update`, before anything of it is stored (its old state kept by a blend).
#include <cfloat>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <immintrin.h>
#include <vector>

#include "layout.h"

namespace {

constexpr int LANES = 16;
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
  const float* __restrict vr;
  float* __restrict lr;  // column by column: link lk's column c at c·links + lk
  const float *__restrict mt, *__restrict lt;
  const int32_t* __restrict vi;
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

// ---- 16 links at once ----

// (the host's gather instruction where it has one: g++ builds a gather from 16 loads and inserts otherwise)
inline vf gather(const float* base, vi at) {
#ifdef __AVX512F__
  return (vf)_mm512_i32gather_ps((__m512i)at, base, 4);
#else
  vf r;
  for (int i = 0; i < LANES; ++i) r[i] = base[at[i]];
  return r;
#endif
}
inline vi gather(const int32_t* base, vi at) {
#ifdef __AVX512F__
  return (vi)_mm512_i32gather_epi32((__m512i)at, base, 4);
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

// Links lk … lk+15 along the common path; returns the lanes off it (a large-angle link, a regime switch into the
// large angle, an end rotation beyond atan's series), whose state it leaves as it was, and sets `diverged`.
inline vi link_group(const Regions& s, int lk, float prev_dt, float max_strain, int& diverged) {
  const int L = s.links;
  const vi n = load(s.li + lk + LI_NEG * L), p = load(s.li + lk + LI_POS * L), axis = load(s.li + lk + LI_AXIS * L);
  const vi flags = load(s.li + lk + LI_FLAGS * L), vn = n * VR_W, vp = p * VR_W, lt = load(s.li + lk + LI_LMAT * L) * LT_W;
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
  const vi off = ~(small & series_applies(q2));
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
      store(at, sel(off, load(at), k == 0 ? out[j].x : (k == 1 ? out[j].y : out[j].z)));
    }
  store(s.lr + lk + LR_STRAIN * L, sel(off, load(s.lr + lk + LR_STRAIN * L), strain));
  store(s.li + lk + LI_FLAGS * L, sel(off, flags, vi{} + (FLAG_SMALL | FLAG_VALID)));
  // 8. divergence on the path's lanes (NaN and inf by the exponent bits, as link_update)
  const vi bad = ~off & ((strain > max_strain) | (((vi)strain & 0x7F800000) == 0x7F800000));
  for (int i = 0; i < LANES; ++i) diverged |= bad[i] != 0;
  return off;
}

template <typename T>
void transpose(T* rows, T* columns, int items, int width, bool into_columns) {
  for (int i = 0; i < items; ++i)
    for (int c = 0; c < width; ++c) {
      if (into_columns) columns[c * items + i] = rows[i * width + c];
      else rows[i * width + c] = columns[c * items + i];
    }
}

// n_steps of every robot's link phase, robot by robot (the robots schedule's order, one thread); the voxels stand
// still, as in scripts/profile_sim.py's `links` segment.
template <bool VECTOR>
long link_steps(float* reals, int32_t* ints, double* f64s, int n_steps) {
  long slow = 0;  // links updated by link_update
  const int32_t* h = ints;
  const int links = h[HDR_N_LINKS];
  std::vector<float> lr(size_t(links) * LR_W);
  std::vector<int32_t> li(size_t(links) * LI_W);
  transpose(reals + h[HDR_LR_AT], lr.data(), links, LR_W, true);
  transpose(ints + h[HDR_LI_AT], li.data(), links, LI_W, true);
  const Regions s{reals + h[HDR_VR_AT], lr.data(), reals + h[HDR_MT_AT], reals + h[HDR_LT_AT], ints + h[HDR_VI_AT],
                  li.data(), links};
  int32_t* ri = ints + h[HDR_RI_AT];
  const double* rt = f64s + h[HDR_RT_AT];
  const float max_strain = float(f64s[h[HDR_GP_AT] + GP_MAX_STRAIN]);
  for (int step = 0; step < n_steps; ++step)
    for (int r = 0; r < h[HDR_N_ROBOTS]; ++r) {
      const int l0 = ri[r * RI_W + RI_LSTART], l1 = ri[r * RI_W + RI_LEND];
      const float prev_dt = float(rt[r * RT_W + RT_DTPREV]);
      int diverged = 0, lk = l0;
      if (VECTOR)
        for (; lk + LANES <= l1; lk += LANES) {
          const vi off = link_group(s, lk, prev_dt, max_strain, diverged);
          for (int i = 0; i < LANES; ++i)
            if (off[i]) {
              diverged |= link_update(s, lk + i, prev_dt, max_strain);
              ++slow;
            }
        }
      for (; lk < l1; ++lk, ++slow) diverged |= link_update(s, lk, prev_dt, max_strain);
      if (diverged) ri[r * RI_W + RI_STATUS] = STATUS_DIVERGED;
    }
  transpose(reals + h[HDR_LR_AT], lr.data(), links, LR_W, false);
  transpose(ints + h[HDR_LI_AT], li.data(), links, LI_W, false);
  return slow;
}

}  // namespace

// Each returns how many link-steps went through link_update (all of them for the scalar one).
extern "C" long link_steps_scalar(float* reals, int32_t* ints, double* f64s, int n) {
  return link_steps<false>(reals, ints, f64s, n);
}
extern "C" long link_steps_vector(float* reals, int32_t* ints, double* f64s, int n) {
  return link_steps<true>(reals, ints, f64s, n);
}
