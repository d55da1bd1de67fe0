// One face sweep as a CPU kernel: the values of ``_kernel._sweep_face_loop`` (the same inputs
// and arithmetic; the isotropic step scheme's fluence sums regrouped by distinct |L|, equal to
// rounding), written where XLA's loops cannot go: the planes visited one residue chain at a
// time, and per row tile the (p, q) shift, the fog step and the sums of one direction in one
// vectorised pass, the e^{-τ|L|} factors once per node and distinct |L|, the surfaces'
// blocking and irradiance only where there are surfaces.  ``sweep_blocked`` serves the
// isotropic step scheme on large faces (blocks of directions, each swept through the whole
// face, shared among threads), ``unit`` on small ones; ``unit_general`` the linear scheme and
// anisotropic fog (a source per direction from the node's channels, Λ's angular moments).
// ``unit`` and ``unit_general`` take all directions per plane, the tiles of each plane shared
// among threads.
//
// Built by ``_native.py`` with the machine's C++ compiler on first use, against jaxlib's XLA
// FFI headers; registered as the custom call "difffog_sweep_face_<hash>" (CPU).  Derivatives
// never come here: the sweep's JVP and transposes are JAX programs (``_kernel``).  The build
// compiles this file three times at once, DIFFFOG_PART=0 for the handler (XLA's FFI headers),
// 1 for float, 2 for double, and links the three; without DIFFFOG_PART it is the whole library.
#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <cstdlib>
#include <memory>
#include <thread>
#include <type_traits>
#include <vector>

#include "native_common.h"

#ifndef DIFFFOG_PART
#define DIFFFOG_PART -1
#endif
#if DIFFFOG_PART <= 0
#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;
#endif

// named (the handler's object calls ``sweep<float>`` and ``sweep<double>`` in the other two),
// hidden from the library's exports
namespace __attribute__((visibility("hidden"))) difffog_sweep {

using difffog_native::em1;  // (``native_common.h``: libmvec's vector expm1 where glibc has it)

struct Dims {
  int64_t M, nw, nu, nv, ns, D, K, nb, s0, s1, threads, tile;
  bool surfaces, per_w, per_u, per_v, att_in, fl_in;
  // the general form (anisotropic fog, the linear scheme): Q has C = 1 + J (+ 3) channels per
  // node, the isotropic source, J that direction d weights by table[d] (the NK moments first),
  // and with the linear scheme the slope h∇Q; Λ has 1 + NK channels.  C = 1, !lin: the
  // isotropic step scheme (``sweep_blocked``, ``unit``).
  int64_t C, J, NK;
  bool lin;
  // Q, B, Λ and E in the world frame (``world``): face node (w, u, v) is world node
  // wb + w·sw + u·su + v·sv (an axis permutation and a flip: ``_kernel.to_face``), so that
  // the face's copies (and XLA's transposes to and from them) are not needed; else the face
  // frame, node (w·nu + u)·nv + v
  bool world;
  int64_t wb, sw, su, sv;
};

// Where face node (p, u, v)'s Q, B, Λ and E lie in their arrays (in nodes).
inline int64_t node_at(const Dims& g, int64_t p, int64_t u, int64_t v) {
  return g.world ? g.wb + p * g.sw + u * g.su + v * g.sv : (p * g.nu + u) * g.nv + v;
}

// Rows [u0, u0 + rows) of face plane p of a one-channel array (B, or the isotropic Q) as a
// contiguous tile (rows, nv): the world frame's gather.
template <typename T>
void gather(const Dims& g, const T* x, int64_t p, int64_t u0, int64_t rows, T* out) {
  for (int64_t r = 0; r < rows; ++r)
    for (int64_t v = 0; v < g.nv; ++v) out[r * g.nv + v] = x[node_at(g, p, u0 + r, v)];
}

template <typename T>
struct Args {
  const T *Q, *B, *tau, *normal, *bc, *length_k, *weight, *unit, *table, *slope;
  const uint8_t *bits, *free, *surf;
  const int32_t *kidx, *start;
  const int32_t* sub = nullptr;  // the sub-stepped scheme's crossings' origins (M − 1, D, 2)
  T *lam, *irr, *exit, *scratch;
  // the surfaces' records made with the plan (``_native.surface_records``, float32's 16-lane
  // layout; ``sweep_blocked``), or null: the blocked sweep makes them at every call
  const int32_t* rec_index = nullptr;  // (nw, nu, nv / 16 + 1): a row vector's record or -1
  const uint8_t* rec_touch = nullptr;  // (R,)
  const uint8_t* rec_any = nullptr;    // (R, nb)
  const float* rec_normal = nullptr;   // (R, 3, 16)
  const uint32_t* rec_bits = nullptr;  // (R, ceil(D / 32), 16)
};

// The sweep visits ns·M planes; plane i of the sweep is the face's plane ``source(i)``, or -1
// for the zero padding after the last plane of an open sweep axis.  A periodic axis is swept
// in wrap order, its first planes a warm-up ending with planes 0..nw-1.
inline int64_t source(const Dims& g, int64_t i) {
  const int64_t total = g.ns * g.M;
  if (g.per_w) return ((i - (total - g.nw)) % g.nw + g.nw) % g.nw;
  return i < g.nw ? i : -1;
}

// Whether plane i's Λ and E are returned (not a warm-up plane, not padding).
inline bool kept(const Dims& g, int64_t i) {
  const int64_t total = g.ns * g.M;
  return g.per_w ? i >= total - g.nw : i < g.nw;
}

// The tile's factor em = e^{-τ} − 1 per node and distinct |L| (τ the half-segment's depth).
template <typename T>
void tables(const T* tau, const T* length_k, int64_t K, int64_t n, T* em) {
  for (int64_t k = 0; k < K; ++k) {
    const T len = length_k[k];
    T* e = em + k * n;
#pragma omp simd
    for (int64_t i = 0; i < n; ++i) e[i] = em1(-(tau[i] * len));
  }
}

// A tile's per-node data in the layouts its passes read: pass[j] (a ray goes on from fog nodes
// and, with surfaces, shells), and with surfaces the face frame's normal (nw, nu, nv, 3) and
// blocking bytes (nw, nu, nv, nb) made planar (3 n, nb n), and where ``special`` is given the
// nodes where surfaces matter (a SURFACE node, a normal or a set bit).
template <typename T, bool SURF>
void node_data(const Dims& g, const Args<T>& a, int64_t off, int64_t n, uint8_t* pass, T* nrm,
               uint8_t* bits, uint8_t* special) {
  for (int64_t j = 0; j < n; ++j)
    pass[j] = uint8_t((a.free[off + j] != 0) || (SURF && a.surf[off + j] != 0));
  if (!SURF) return;
  const T* nsrc = a.normal + off * 3;
  const uint8_t* bsrc = a.bits + off * g.nb;
  for (int64_t j = 0; j < n; ++j) {
    bool sp = a.surf[off + j] != 0;
    for (int c = 0; c < 3; ++c) sp |= (nrm[c * n + j] = nsrc[3 * j + c]) != T(0);
    for (int64_t b = 0; b < g.nb; ++b) sp |= (bits[b * n + j] = bsrc[g.nb * j + b]) != 0;
    if (special) special[j] = uint8_t(sp);
  }
}

// (1 − e^{-t})/t: ``ratio`` (the caller's closed form, −(e^{-t} − 1)/t) or, below t = 1e-3,
// ``one_minus_exp_over``'s series
template <typename T>
inline T avg_or_series(T t, T ratio) {
  const bool small = std::fabs(t) < T(1e-3);
  return small ? T(1) - t / T(2) + t * t / T(6) - t * t * t / T(24) : ratio;
}

// (1 − e^{-t})/t from x = e^{-t} − 1
template <typename T>
inline T avg(T t, T x) {
  return avg_or_series(t, -x / (std::fabs(t) < T(1e-3) ? T(1) : t));
}

// Blocking bits in words as wide as T (so that a loop that reads them has T's lanes and
// vectorises whole 64-byte vectors): WB bits a word, ``blocking_words`` words for D directions
template <typename T>
using Word = std::conditional_t<sizeof(T) == 8, uint64_t, uint32_t>;

template <typename T>
constexpr int64_t WB = 8 * int64_t(sizeof(Word<T>));

template <typename T>
inline int64_t blocking_words(int64_t D) {
  return (D + WB<T> - 1) / WB<T>;
}

// The step scheme's update of one ray at one node (``unit``, ``block_tile``): the arriving
// radiance r_mid (the carry, shifted), the node's Q (qt) and e^{-τ|L|} − 1 (x, with ATT); it
// returns the ray leaving (0 where it does not go on) and with FL sums the fluence's s
// (Σ w (R − Q) with a fog step, Σ w R̄ without).  The fog-only form:
template <typename T, bool ATT, bool FL>
inline __attribute__((always_inline)) T step_fog(T r_mid, T qt, T x, T w, bool pass, T& s) {
  T r_out = r_mid;
  if (ATT) {
    const T r_arr = r_mid + x * (r_mid - qt);
    if (FL) s += w * (r_mid - qt);
    r_out = r_arr + x * (r_arr - qt);
  } else if (FL) {
    s += r_mid * w;
  }
  return pass ? r_out : T(0);
}

// and with surfaces: a blocked arrival is the surface's radiosity bt (only the departure half
// lies in the fog: its R̄ goes through c, the blocked ones' weights, not s), E sums the
// arriving radiance by cos (cosw = max(−L·n, 0)·w).
template <typename T, bool ATT, bool FL>
inline __attribute__((always_inline)) T step_surf(T r_mid, T qt, T bt, T x, bool blocked,
                                                  T cosw, T w, bool pass, T& s, T& c, T& E) {
  T r_arr = ATT ? r_mid + x * (r_mid - qt) : r_mid;
  r_arr = blocked ? bt : r_arr;
  if (ATT && FL) {
    s += blocked ? T(0) : w * (r_mid - qt);
    c += blocked ? w : T(0);
  } else if (FL) {  // no fog step: R̄ is the arriving radiance
    s += w * (blocked ? bt : r_mid);
  }
  E += r_arr * cosw;
  const T r_through = ATT ? r_arr + x * (r_arr - qt) : r_arr;
  return pass ? r_through : T(0);
}

// One unit: rows [u0, u1) of sweep plane i (face plane p = source(i) >= 0), every direction:
// src and dst are the chain's carries (D, PU, PV) before and after the plane.
//
// The direction loop runs over whole rows, one 64-byte vector at a time (per direction the
// rows read and written are each one contiguous block).  Two things keep it short:
// - Λ is Σ_d w_d R̄_d with R̄_d = Q + (R_d − Q)·a2_k, or Q + (B − Q)·a1_k after a blocked
//   arrival (a2_k = (1 − e^{−2τ_k})/(2τ_k), a1_k = (1 − e^{−τ_k})/τ_k for the direction's
//   distinct |L|), so the loop only sums S_k += w_d (R_d − Q) per |L| (and C_k += w_d over the
//   blocked ones) and Λ = Q Σ_d w_d + Σ_k [a2_k S_k + a1_k (B − Q) C_k] once per node afterwards:
//   the same sum, regrouped;
// - only a vector that holds a node where surfaces matter (a SURFACE node, a set blocking bit
//   or a normal: the shell around the shapes) takes the form with surfaces: a blocked arrival
//   (the surface's radiosity B instead of the ray), E by cos; the others the fog-only form
//   (a fog node's blocking bits and normal are 0, where the two forms agree).
template <typename T, bool ATT, bool SURF, bool FL>
void unit(const Dims& g, const Args<T>& a, const T* src, T* dst, int64_t i, int64_t p,
          int64_t u0, int64_t u1, std::vector<T>& work, std::vector<int32_t>& flags) {
  const int64_t M = g.M, nu = g.nu, nv = g.nv, PU = nu + 2 * M, PV = nv + 2 * M;
  const int64_t rows = u1 - u0, n = rows * nv;
  const int64_t off = (p * nu + u0) * nv;
  // Q and B of the tile's nodes: in place (face frame) or gathered (world frame; scratch)
  const T* Q = g.world ? nullptr : a.Q + off;
  const T* B = g.world ? nullptr : a.B + off;
  const T* tau = a.tau + off;
  const int64_t K = ATT ? g.K : 0;
  const int64_t KC = SURF ? K : 0;  // the blocked weights C_k
  // scratch: factors em (K n), sums S (K n), C (K n with surfaces), Λ and E (2 n), normal (3 n
  // with surfaces); words as wide as T (so that every array a loop reads has T's lanes, and
  // the loops vectorise one vector at a time, not four): pass (n), blocking bits (NW n, bit d
  // of node j in word (d / WB) n + j, with surfaces); bytes: pass, special (2 n), blocking
  // bits (nb n)
  using W = Word<T>;
  const int64_t NW = SURF ? blocking_words<T>(g.D) : 0;
  const int64_t nbytes = 2 * n + (SURF ? g.nb * n : 0);
  const int64_t NQ = g.world ? 2 : 0;  // the gathered Q and B
  work.resize(size_t((2 * K + KC + 2 + (SURF ? 3 : 0) + 1 + NW + NQ) * n +
                     (nbytes + sizeof(T) - 1) / sizeof(T)));
  T* em = work.data();
  T* S = em + K * n;
  T* C = S + K * n;
  T* accl = C + KC * n;
  T* acci = accl + n;
  T* nrm = acci + n;
  if (g.world) {
    T* qw = nrm + (SURF ? 3 * n : 0);
    gather(g, a.Q, p, u0, rows, qw);
    gather(g, a.B, p, u0, rows, qw + n);
    Q = qw;
    B = qw + n;
  }
  W* passw = reinterpret_cast<W*>(nrm + (SURF ? 3 * n : 0) + NQ * n);
  W* bitw = passw + n;
  uint8_t* pass = reinterpret_cast<uint8_t*>(bitw + NW * n);
  uint8_t* special = pass + n;
  uint8_t* bits = special + n;
  if (ATT) tables<T>(tau, a.length_k, K, n, em);
  std::fill(S, S + (K + KC) * n, T(0));
  std::fill(accl, accl + 2 * n, T(0));
  node_data<T, SURF>(g, a, off, n, pass, nrm, bits, special);
  for (int64_t j = 0; j < n; ++j) passw[j] = W(pass[j]);
  std::fill(bitw, bitw + NW * n, W(0));
  for (int64_t b = 0; b < (SURF ? g.nb : 0); ++b) {
    const uint8_t* src_b = bits + b * n;
    W* dst_w = bitw + (8 * b / WB<T>) * n;
    const int sh = int((8 * b) % WB<T>);
    for (int64_t j = 0; j < n; ++j) dst_w[j] |= W(src_b[j]) << sh;
  }
  // each row as whole vectors (64 bytes) and a remainder; a vector that holds a node where
  // surfaces matter (a SURFACE node, a set blocking bit or a normal: the shell around the
  // shapes) takes the form with surfaces, the others the fog-only form (the same for a fog
  // node, whose blocking bits and normal are 0).  ``flags``: per row, one per vector.
  constexpr int64_t VW = 64 / int64_t(sizeof(T));
  const int64_t nvec = nv / VW, nch = nvec + 1;  // + the remainder's flag
  flags.assign(size_t(rows * nch), 0);
  if (SURF)
    for (int64_t r = 0; r < rows; ++r)
      for (int64_t v = 0; v < nv; ++v) flags[size_t(r * nch + v / VW)] |= special[r * nv + v];
  T wsum = T(0);
  for (int64_t d = 0; d < g.D; ++d) {
    const int64_t k = ATT ? a.kidx[d] : 0;
    const T w = a.weight[d];
    wsum += w;
    const int64_t su = a.start[2 * d], sv = a.start[2 * d + 1];
    const T* sd = src + (d * PU + u0 + su) * PV + sv;  // the plane's rows, shifted by (p, q)
    T* dd = dst + (d * PU + u0 + M) * PV + M;
    const T ux = a.unit[3 * d], uy = a.unit[3 * d + 1], uz = a.unit[3 * d + 2];
    const W* bd = bitw + (d / WB<T>) * n;
    const int bit = int(d % WB<T>);
    for (int64_t r = 0; r < rows; ++r) {
      const T* rs = sd + r * PV;
      T* rd = dd + r * PV;
      const int64_t o = r * nv;
      const T* e = em + k * n + o;
      const T* q = Q + o;
      const W* ps = passw + o;
      T* sk = S + k * n + o;
      T* al = accl + o;
      const T* bb = B + o;
      const W* bl = bd + o;
      const T *n0 = nrm + o, *n1 = nrm + n + o, *n2 = nrm + 2 * n + o;
      T* ck = C + k * n + o;
      T* ai = acci + o;
      const int32_t* flag = flags.data() + r * nch;
      auto fog = [&](int64_t v) __attribute__((always_inline)) {
        rd[v] = step_fog<T, ATT, FL>(rs[v], q[v], ATT ? e[v] : T(0), w, ps[v] != 0,
                                     ATT ? sk[v] : al[v]);
      };
      auto surf = [&](int64_t v) __attribute__((always_inline)) {
        const T cosw = std::max(-(n0[v] * ux + n1[v] * uy + n2[v] * uz), T(0)) * w;
        rd[v] = step_surf<T, ATT, FL>(rs[v], q[v], bb[v], ATT ? e[v] : T(0),
                                      ((bl[v] >> bit) & 1) != 0, cosw, w, ps[v] != 0,
                                      ATT ? sk[v] : al[v], ck[v], ai[v]);
      };
      for (int64_t c = 0; c < nvec; ++c) {
        const int64_t v0 = c * VW;
        if (SURF && flag[c]) {
#pragma omp simd
          for (int64_t l = 0; l < VW; ++l) surf(v0 + l);
        } else {
#pragma omp simd
          for (int64_t l = 0; l < VW; ++l) fog(v0 + l);
        }
      }
      if (SURF && flag[nvec]) {
        for (int64_t v = nvec * VW; v < nv; ++v) surf(v);
      } else {
        for (int64_t v = nvec * VW; v < nv; ++v) fog(v);
      }
    }
  }
  if (!kept(g, i)) return;
  if (ATT && FL) {  // Λ = Q Σ_d w_d + Σ_k [a2_k S_k + a1_k (B − Q) C_k]
    for (int64_t j = 0; j < n; ++j) accl[j] = Q[j] * wsum;
    for (int64_t k = 0; k < K; ++k) {
      const T len = a.length_k[k];
      const T* e = em + k * n;
      const T* sk = S + k * n;
#pragma omp simd
      for (int64_t j = 0; j < n; ++j) {
        const T x = e[j];
        accl[j] += avg(T(2) * (tau[j] * len), x * (x + T(2))) * sk[j];
      }
      if (!SURF) continue;
      const T* ck = C + k * n;
#pragma omp simd
      for (int64_t j = 0; j < n; ++j)
        accl[j] += ck[j] != T(0) ? avg(tau[j] * len, e[j]) * (B[j] - Q[j]) * ck[j] : T(0);
    }
  }
  if (!g.world) {
    std::memcpy(a.lam + off, accl, size_t(n) * sizeof(T));
    std::memcpy(a.irr + off, acci, size_t(n) * sizeof(T));
    return;
  }
  for (int64_t r = 0; r < rows; ++r)
    for (int64_t v = 0; v < nv; ++v) {
      const int64_t w = node_at(g, p, u0 + r, v);
      a.lam[w] = accl[r * nv + v];
      a.irr[w] = acci[r * nv + v];
    }
}


// φ = (1 − e^{-t})/t and ψ = (1 − φ)/t (``_numerics.linear_source_terms``: their Taylor series
// below t = 0.5, where the closed forms cancel; x = e^{-t} − 1).
template <typename T>
inline void phi_psi(T t, T x, T& phi, T& psi) {
  if (std::fabs(t) < T(0.5)) {
    T ps = T(0), ss = T(0), pw = T(1), prev = T(0), fact = T(1);  // pw = τ^n, prev = τ^(n−1)
    for (int n = 0; n < 11; ++n) {
      if (n) fact *= T(n);
      const T a = ((n & 1) ? T(-1) : T(1)) / fact;
      ps += a / T(n + 1) * pw;                // a τ^n/(n+1)
      if (n >= 1) ss -= a / T(n + 1) * prev;  // −a τ^(n−1)/(n+1)
      prev = pw;
      pw *= t;
    }
    phi = ps;
    psi = ss;
  } else {
    phi = -x / t;
    psi = (t + x) / (t * t);
  }
}

// The general form of ``unit`` (same rows and carries): a direction's source from the
// node's channels, Q_0 + Σ_j table[d, j] Q_j; with the linear scheme (LIN) the source linear
// along the segment (slope s = L·h∇Q: R at the node r_mid + em·a + ω s, leaving it R + em·b +
// ω s, mean q + φ(a + b)/2 − ψ s/2, a = r_mid − q + s/2, b = R − q, ω = τψ/2:
// ``_kernel._linear_node``); Λ and its NK moments Σ_d w_d Ỹ_k(d) R̄_d summed directly, per row
// in passes over small row buffers (so that each loop vectorises); the surfaces' blocking and
// irradiance in the same pass.
template <typename T, bool ATT, bool SURF, bool FL, bool LIN>
void unit_general(const Dims& g, const Args<T>& a, const T* src, T* dst, int64_t i, int64_t p,
                  int64_t u0, int64_t u1, std::vector<T>& work, std::vector<int32_t>&) {
  const int64_t M = g.M, nu = g.nu, nv = g.nv, PU = nu + 2 * M, PV = nv + 2 * M;
  const int64_t rows = u1 - u0, n = rows * nv, C = g.C, J = g.J, NK = g.NK;
  const int64_t off = (p * nu + u0) * nv;
  const T* B = g.world ? nullptr : a.B + off;
  const T* tau = a.tau + off;
  const int64_t K = ATT ? g.K : 0;
  const int64_t L1 = 1 + NK;
  const int64_t NQ = g.world ? 1 : 0;  // B gathered (world frame)
  // scratch: channels (C n), per |L| factors em, A, Bf, W (4 K n), Λ and moments (L1 n), E (n),
  // normal (3 n), row buffers q, s, R̄ (3 nv); bytes: pass (n), blocking bits (nb n)
  const int64_t nbytes = n + (SURF ? g.nb * n : 0);
  work.resize(size_t((C + 4 * K + L1 + 1 + (SURF ? 3 : 0) + NQ) * n + 3 * nv +
                     (nbytes + sizeof(T) - 1) / sizeof(T)));
  T* Qc = work.data();
  T* em = Qc + C * n;
  T* fa = em + K * n;   // step: (1 − e^{-2τ})/2τ; linear: φ(τ)
  T* fb = fa + K * n;   // step: (1 − e^{-τ})/τ;   linear: ψ(τ)
  T* fw = fb + K * n;   // linear: τψ/2
  T* acc = fw + K * n;  // Λ, then the moments (L1 n)
  T* acci = acc + L1 * n;
  T* nrm = acci + n;
  T* qrow = nrm + (SURF ? 3 * n : 0);
  T* srow = qrow + nv;
  T* arow = srow + nv;
  if (g.world) {
    gather(g, a.B, p, u0, rows, arow + nv);
    B = arow + nv;
  }
  uint8_t* pass = reinterpret_cast<uint8_t*>(arow + nv + NQ * n);
  uint8_t* bits = pass + n;
  for (int64_t j = 0; j < n; ++j) {  // channels first
    const T* qn = a.Q + node_at(g, p, u0 + j / nv, j % nv) * C;
    for (int64_t c = 0; c < C; ++c) Qc[c * n + j] = qn[c];
  }
  for (int64_t k = 0; k < K; ++k) {
    const T len = a.length_k[k];
    T *e = em + k * n, *x1 = fa + k * n, *x2 = fb + k * n, *x3 = fw + k * n;
#pragma omp simd
    for (int64_t j = 0; j < n; ++j) e[j] = em1(-(tau[j] * len));
    for (int64_t j = 0; j < n; ++j) {
      const T t = tau[j] * len, x = e[j];
      if (LIN) {
        phi_psi(t, x, x1[j], x2[j]);
        x3[j] = T(0.5) * t * x2[j];
      } else {
        x1[j] = avg(T(2) * t, x * (x + T(2)));
        x2[j] = avg(t, x);
      }
    }
  }
  std::fill(acc, acc + (L1 + 1) * n, T(0));
  node_data<T, SURF>(g, a, off, n, pass, nrm, bits, nullptr);
  for (int64_t d = 0; d < g.D; ++d) {
    const int64_t k = ATT ? a.kidx[d] : 0;
    const T w = a.weight[d];
    const T* tab = a.table + d * J;
    const T* sd = src + (d * PU + u0 + a.start[2 * d]) * PV + a.start[2 * d + 1];
    T* dd = dst + (d * PU + u0 + M) * PV + M;
    const T ux = a.unit[3 * d], uy = a.unit[3 * d + 1], uz = a.unit[3 * d + 2];
    const int bit = int(d & 7);
    for (int64_t r = 0; r < rows; ++r) {
      const int64_t o = r * nv;
      const T* rs = sd + r * PV;
      T* rd = dd + r * PV;
      // this direction's source along the row, and its slope
      std::memcpy(qrow, Qc + o, size_t(nv) * sizeof(T));
      for (int64_t c = 0; c < J; ++c) {
        const T tc = tab[c];
        const T* qc = Qc + (1 + c) * n + o;
#pragma omp simd
        for (int64_t v = 0; v < nv; ++v) qrow[v] += tc * qc[v];
      }
      if (LIN) {
        const T s0 = a.slope[3 * d], s1 = a.slope[3 * d + 1], s2 = a.slope[3 * d + 2];
        const T *g0 = Qc + (1 + J) * n + o, *g1 = g0 + n, *g2 = g1 + n;
#pragma omp simd
        for (int64_t v = 0; v < nv; ++v) srow[v] = s0 * g0[v] + s1 * g1[v] + s2 * g2[v];
      }
      const T *e = em + k * n + o, *x1 = fa + k * n + o, *x2 = fb + k * n + o,
              *x3 = fw + k * n + o;
      const T* bb = B + o;
      const uint8_t* ps = pass + o;
      const uint8_t* bl = bits + (d >> 3) * n + o;
      const T *n0 = nrm + o, *n1 = nrm + n + o, *n2 = nrm + 2 * n + o;
      T* ai = acci + o;
#pragma omp simd
      for (int64_t v = 0; v < nv; ++v) {
        const T r_mid = rs[v], q = qrow[v];
        T r_arr = r_mid, r_avg = r_mid, r_thr = r_mid, x = T(0);
        if (ATT) {
          x = e[v];
          if (LIN) {
            const T sl = srow[v], om = x3[v];
            const T aa = r_mid - q + T(0.5) * sl;
            r_arr = r_mid + x * aa + om * sl;
            const T bq = r_arr - q;
            r_thr = r_arr + x * bq + om * sl;
            r_avg = q + T(0.5) * x1[v] * (aa + bq) - T(0.5) * x2[v] * sl;
          } else {
            r_arr = r_mid + x * (r_mid - q);
            r_avg = q + (r_mid - q) * x1[v];
          }
        }
        if (SURF) {
          const bool blocked = ((bl[v] >> bit) & 1) != 0;
          const T bt = bb[v];
          r_arr = blocked ? bt : r_arr;
          if (ATT && FL)  // blocked: only the departure half lies in the fog
            r_avg = blocked ? q + (bt - q) * (LIN ? x1[v] : x2[v]) : r_avg;
          else
            r_avg = r_arr;
          if (ATT && LIN) r_thr = blocked ? bt + x * (bt - q) : r_thr;
          const T ldotn = n0[v] * ux + n1[v] * uy + n2[v] * uz;
          ai[v] += r_arr * (std::max(-ldotn, T(0)) * w);
        }
        if (!(ATT && LIN)) r_thr = ATT ? r_arr + x * (r_arr - q) : r_arr;
        arow[v] = r_avg;
        rd[v] = ps[v] ? r_thr : T(0);
      }
      if (!FL) continue;
      T* al = acc + o;
#pragma omp simd
      for (int64_t v = 0; v < nv; ++v) al[v] += w * arow[v];
      for (int64_t c = 0; c < NK; ++c) {  // the moments: w_d Ỹ_c(d) R̄_d
        const T wc = w * tab[c];
        T* mc = acc + (1 + c) * n + o;
#pragma omp simd
        for (int64_t v = 0; v < nv; ++v) mc[v] += wc * arow[v];
      }
    }
  }
  if (!kept(g, i)) return;
  for (int64_t j = 0; j < n; ++j) {
    const int64_t w = node_at(g, p, u0 + j / nv, j % nv);
    T* lam = a.lam + w * L1;
    for (int64_t c = 0; c < L1; ++c) lam[c] = acc[c * n + j];
    a.irr[w] = acci[j];
  }
}

template <typename T>
using UnitFn = void (*)(const Dims&, const Args<T>&, const T*, T*, int64_t, int64_t, int64_t,
                        int64_t, std::vector<T>&, std::vector<int32_t>&);

template <typename T>
UnitFn<T> pick(bool att, bool surf, bool fl) {
  const int key = (att ? 4 : 0) | (surf ? 2 : 0) | (fl ? 1 : 0);
  switch (key) {
    case 0: return unit<T, false, false, false>;
    case 1: return unit<T, false, false, true>;
    case 2: return unit<T, false, true, false>;
    case 3: return unit<T, false, true, true>;
    case 4: return unit<T, true, false, false>;
    case 5: return unit<T, true, false, true>;
    case 6: return unit<T, true, true, false>;
    default: return unit<T, true, true, true>;
  }
}

template <typename T, bool LIN>
UnitFn<T> pick_general_(bool att, bool surf, bool fl) {
  const int key = (att ? 4 : 0) | (surf ? 2 : 0) | (fl ? 1 : 0);
  switch (key) {
    case 0: return unit_general<T, false, false, false, LIN>;
    case 1: return unit_general<T, false, false, true, LIN>;
    case 2: return unit_general<T, false, true, false, LIN>;
    case 3: return unit_general<T, false, true, true, LIN>;
    case 4: return unit_general<T, true, false, false, LIN>;
    case 5: return unit_general<T, true, false, true, LIN>;
    case 6: return unit_general<T, true, true, false, LIN>;
    default: return unit_general<T, true, true, true, LIN>;
  }
}

template <typename T>
UnitFn<T> pick_general(bool att, bool surf, bool fl, bool lin) {
  return lin ? pick_general_<T, true>(att, surf, fl) : pick_general_<T, false>(att, surf, fl);
}

// Rewrite the M border rows (axis 0 of a (PU, PV) plane) or columns by wrapping the interior
// [M, M + n): padded index i takes interior index ((i − M) mod n) + M.
template <typename T>
void wrap(T* pl, int64_t PU, int64_t PV, int64_t M, int64_t n, bool rows) {
  auto src_of = [&](int64_t i) { return ((i - M) % n + n) % n + M; };
  if (rows) {
    for (int64_t i = 0; i < M; ++i) std::memcpy(pl + i * PV, pl + src_of(i) * PV, PV * sizeof(T));
    for (int64_t i = n + M; i < n + 2 * M; ++i)
      std::memcpy(pl + i * PV, pl + src_of(i) * PV, PV * sizeof(T));
  } else {
    for (int64_t r = 0; r < PU; ++r) {
      T* row = pl + r * PV;
      for (int64_t i = 0; i < M; ++i) row[i] = row[src_of(i)];
      for (int64_t i = n + M; i < n + 2 * M; ++i) row[i] = row[src_of(i)];
    }
  }
}

// A carried plane's border on the periodic sides, from its interior (rows, then columns:
// corners included).
template <typename T>
void wrap_periodic(const Dims& g, T* pl) {
  const int64_t M = g.M, PU = g.nu + 2 * M, PV = g.nv + 2 * M;
  if (g.per_u) wrap(pl, PU, PV, M, g.nu, true);
  if (g.per_v) wrap(pl, PU, PV, M, g.nv, false);
}

// A carried plane's border (the M rows and columns around the interior, which every plane's
// step writes whole) set to ``val``: the other carry of a direction before its chain's first
// plane, whose border on the open sides holds bc[d] from plane to plane (on the periodic
// ones each step wraps it from the interior).
template <typename T>
void fill_border(const Dims& g, T* pl, T val) {
  const int64_t M = g.M, PU = g.nu + 2 * M, PV = g.nv + 2 * M;
  std::fill(pl, pl + M * PV, val);
  std::fill(pl + (M + g.nu) * PV, pl + PU * PV, val);
  for (int64_t u = M; u < M + g.nu; ++u) {
    std::fill(pl + u * PV, pl + u * PV + M, val);
    std::fill(pl + u * PV + M + g.nv, pl + (u + 1) * PV, val);
  }
}

// A chain's carry before its first plane (D, PU, PV): on a periodic sweep axis the plane's own
// source (the equilibrium guess for horizontal rays that never leave the domain), else the
// boundary radiance bc[d]; bc[d] on the open sides' border, wrapped on periodic ones.
template <typename T>
void initial_direction(const Dims& g, const Args<T>& a, int64_t m, int64_t d, T* pl) {
  const int64_t M = g.M, PU = g.nu + 2 * M, PV = g.nv + 2 * M;
  const int64_t C = g.C;
  const int64_t p0 = g.per_w ? source(g, m) : -1;
  std::fill(pl, pl + PU * PV, a.bc[d]);
  if (p0 < 0) return;
  const T* tab = a.table + d * g.J;  // direction d's source: Q_0 + Σ_j table[d, j] Q_j
  for (int64_t u = 0; u < g.nu; ++u)
    for (int64_t v = 0; v < g.nv; ++v) {
      const T* qn = a.Q + node_at(g, p0, u, v) * C;
      T q = qn[0];
      for (int64_t c = 0; c < g.J; ++c) q += tab[c] * qn[1 + c];
      pl[(u + M) * PV + M + v] = q;
    }
  wrap_periodic(g, pl);
}

template <typename T>
void initial(const Dims& g, const Args<T>& a, int64_t m, T* buf) {
  const int64_t PU = g.nu + 2 * g.M, PV = g.nv + 2 * g.M;
  for (int64_t d = 0; d < g.D; ++d) initial_direction(g, a, m, d, buf + d * PU * PV);
}

// ---------------------------------------------------------------------------------------------
// The isotropic step scheme by direction blocks.
// The directions, ordered by |L|, are cut into a few blocks; each block is swept alone through
// every plane of every chain, its carries (two planes per direction) kept from plane to plane,
// and a plane's node data (τ, Q, the pass flags, Λ and E) read once per block rather than
// once per direction; e^{-τ|L|} − 1 once per block and |L|.  The blocks are shared among the
// threads (a fixed share each), each summing Λ and E into its own face-sized arrays, added
// at the end.  Swept all together per row tile (as ``unit`` does), the D directions' carries
// (18 MB at N = 128, M = 5) went through the last-level cache at every plane, and their loads
// and stores took half of the sweep's time (a profile of fog-balls); by blocks, per plane and
// tile each direction's rows are read and written while the tile's node data stay in L1, and
// (since stop 72) one 64-byte vector at a time through all of the block's directions, its node
// data and sums in registers (``block_tile``).

// a block's two carries per direction at most (the block size against the passes over the
// node data; measured: fog without surfaces, N = 128, M = 5, 0.52 / 0.47 / 0.45 s per
// iteration with 16 / 8 / 4 blocks)
constexpr int64_t BLOCK_CARRY_BYTES = 5 * 1024 * 1024;
constexpr int64_t BLOCK_MAX = 32;  // directions per block
// a face with fewer node-and-direction updates goes plane by plane (``unit``): by blocks its
// call's fixed costs (the records, the threads' arrays, the thread starts) outweigh the
// faster loop (stop 72, one face sweep's share of a Jacobi iteration, fog-balls: N = 16,
// M = 2, 1.6·10⁵ updates a face, 2 against 1 ms on two threads; N = 24, M = 2, 3.5·10⁵, 4
// against 5 ms; N = 32, M = 3, 1.6·10⁶, 8-10 against 20 ms)
constexpr int64_t BLOCKED_MIN_UPDATES = int64_t(1) << 18;
// a row tile's rows: 16 KB for six arrays of the tile (chosen for stop 71's loop, which read
// them at every update; ``block_tile`` reads its per-|L| tables once per vector and |L|)
constexpr int64_t BLOCK_TILE_BYTES = 16 * 1024;

// Face planes [p0, p1) of a one-channel array between the world frame (``node_at``) and the
// face frame ((p·nu + u)·nv + v): world → face (``to_face``) or back.  The loops run in blocks
// of 16 along v and along whichever of p and u is the world's smallest stride (when v is not),
// so that both sides are read and written by whole cache lines (a plain loop over v read one
// line per node there).
template <typename T>
void permute(const Dims& g, int64_t p0, int64_t p1, bool to_face, const T* from, T* to) {
  const int64_t nu = g.nu, nv = g.nv;
  const int64_t aw = std::llabs(g.sw), au = std::llabs(g.su), av = std::llabs(g.sv);
  auto move = [&](int64_t p, int64_t u, int64_t v) __attribute__((always_inline)) {
    const int64_t f = (p * nu + u) * nv + v, w = node_at(g, p, u, v);
    if (to_face) to[f] = from[w];
    else to[w] = from[f];
  };
  constexpr int64_t BS = 16;
  if (av <= au && av <= aw) {
    for (int64_t p = p0; p < p1; ++p)
      for (int64_t u = 0; u < nu; ++u)
        for (int64_t v = 0; v < nv; ++v) move(p, u, v);
  } else if (au <= aw) {
    for (int64_t p = p0; p < p1; ++p)
      for (int64_t ub = 0; ub < nu; ub += BS)
        for (int64_t vb = 0; vb < nv; vb += BS)
          for (int64_t v = vb; v < std::min(nv, vb + BS); ++v)
            for (int64_t u = ub; u < std::min(nu, ub + BS); ++u) move(p, u, v);
  } else {
    for (int64_t pb = p0; pb < p1; pb += BS)
      for (int64_t u = 0; u < nu; ++u)
        for (int64_t vb = 0; vb < nv; vb += BS)
          for (int64_t v = vb; v < std::min(nv, vb + BS); ++v)
            for (int64_t p = pb; p < std::min(p1, pb + BS); ++p) move(p, u, v);
  }
}

// The surfaces' data of the 64-byte vectors where they matter (a node that is a SURFACE node,
// has a normal or is blocked for some direction), one record each, built once per sweep: per
// lane the normal and the blocking bits in ``Word``s, planar (3 × VW and NW × VW: bit d % WB of
// word d / WB says whether direction d is blocked there), whether a node has a normal or is a
// SURFACE node (E is summed there) and the OR of the lanes' bytes.  ``index``: per vector of
// each face row (the whole ones and the remainder: nch = nv / VW + 1 per row) its record, or
// -1: the part (the thread that built it) · 2^PART_SHIFT + its number there.
template <typename T>
struct SurfPart {
  std::vector<T> normal;       // (records, 3, VW)
  std::vector<Word<T>> bits;   // (records, NW, VW)
  std::vector<uint8_t> any;    // (records, nb)
  std::vector<uint8_t> touch;  // (records,)
};

constexpr int PART_SHIFT = 40;

// One row vector's record (``SurfVecs::find``).
template <typename T>
struct SurfRec {
  bool touch;
  const uint8_t* any;     // its blocking bits' OR over the lanes, by byte (nb)
  const Word<T>* bits;    // its blocking words (NW, VW)
  const T* normal;        // (3, VW)
};

template <typename T>
struct SurfVecs {
  static constexpr int64_t VW = 64 / int64_t(sizeof(T));
  int64_t nch = 0, nb = 0, NW = 0;
  std::vector<int64_t> index;
  std::vector<SurfPart<T>> parts;
  // or the plan's (Args::rec_*, T = float): one set, numbered in ``rec_index``
  const int32_t* ext_index = nullptr;
  const uint8_t* ext_touch = nullptr;
  const uint8_t* ext_any = nullptr;
  const Word<T>* ext_bits = nullptr;
  const T* ext_normal = nullptr;

  // row vector ``i``'s record ((p·nu + u)·nch + c), false where it has none
  inline bool find(int64_t i, SurfRec<T>& r) const {
    if (ext_index) {
      const int64_t x = ext_index[i];
      if (x < 0) return false;
      r = {ext_touch[x] != 0, ext_any + x * nb, ext_bits + x * NW * VW, ext_normal + x * 3 * VW};
      return true;
    }
    const int64_t ri = index[size_t(i)];
    if (ri < 0) return false;
    const SurfPart<T>& pt = parts[size_t(ri >> PART_SHIFT)];
    const size_t x = size_t(ri & ((int64_t(1) << PART_SHIFT) - 1));
    r = {pt.touch[x] != 0, pt.any.data() + x * size_t(nb), pt.bits.data() + x * size_t(NW * VW),
         pt.normal.data() + x * 3 * VW};
    return true;
  }
};

// Face rows [r0, r1)' records: part ``t`` of ``all`` (and its index for those rows).
template <typename T>
void surf_records(const Dims& g, const Args<T>& a, int64_t r0, int64_t r1, int64_t t,
                  SurfVecs<T>& all) {
  constexpr int64_t VW = SurfVecs<T>::VW;
  const int64_t nv = g.nv, nch = all.nch, nb = g.nb;
  SurfPart<T>& part = all.parts[size_t(t)];
  const size_t guess = size_t((r1 - r0) * nch / 4 + 1);  // records: a quarter of the vectors
  part.normal.reserve(guess * 3 * VW);
  const int64_t NW = blocking_words<T>(g.D);
  part.bits.reserve(guess * NW * VW);
  part.any.reserve(guess * nb);
  part.touch.reserve(guess);
  for (int64_t r = r0; r < r1; ++r)
    for (int64_t c = 0; c < nch; ++c) {
      const int64_t v0 = c * VW, nl = std::min(nv, (c + 1) * VW) - v0, j0 = r * nv + v0;
      if (nl <= 0) {
        all.index[size_t(r * nch + c)] = -1;
        continue;
      }
      // whether any lane matters (branch-free loops over the vector's contiguous data)
      const T* nn = a.normal + 3 * j0;
      const uint8_t* bj = a.bits + nb * j0;
      const uint8_t* sj = a.surf + j0;
      uint8_t blocked = 0, surf = 0;
      T nrm_any = T(0);
      for (int64_t x = 0; x < nb * nl; ++x) blocked |= bj[x];
      for (int64_t x = 0; x < nl; ++x) surf |= sj[x];
      for (int64_t x = 0; x < 3 * nl; ++x) nrm_any += std::fabs(nn[x]);
      const bool touch = surf != 0 || nrm_any != T(0);
      if (!touch && !blocked) {
        all.index[size_t(r * nch + c)] = -1;
        continue;
      }
      const size_t rec = part.touch.size();
      all.index[size_t(r * nch + c)] = (t << PART_SHIFT) + int64_t(rec);
      part.touch.push_back(uint8_t(touch));
      part.normal.resize((rec + 1) * size_t(3 * VW), T(0));
      part.bits.resize((rec + 1) * size_t(NW * VW), 0);
      part.any.resize((rec + 1) * size_t(nb), 0);
      T* nrm = part.normal.data() + rec * 3 * VW;
      Word<T>* w = part.bits.data() + rec * NW * VW;
      uint8_t* any = part.any.data() + rec * nb;
      for (int64_t l = 0; l < nl; ++l)
        for (int x = 0; x < 3; ++x) nrm[x * VW + l] = nn[3 * l + x];
      if (!blocked) continue;
      for (int64_t l = 0; l < nl; ++l)
        for (int64_t k = 0; k < nb; ++k) {  // byte k: directions 8k … 8k + 7
          w[(8 * k / WB<T>) * VW + l] |= Word<T>(bj[l * nb + k]) << ((8 * k) % WB<T>);
          any[k] |= bj[l * nb + k];
        }
    }
}

// Whether direction ``dirs[b]`` begins a run of equal |L| in ``dirs`` (ordered by |L|: kidx)
inline bool run_begins(const int32_t* kidx, const int32_t* dirs, int64_t b) {
  return b == 0 || kidx[dirs[b]] != kidx[dirs[b - 1]];
}

// Rows [u0, u1) of face plane p for the block's nd directions ``dirs`` (ordered by |L|): their
// carries src[b] → dst[b] (PU, PV), and where the plane is kept Λ and E added to lam and irr
// (face frame).
//
// One 64-byte vector of a row at a time, every direction of the block, with the vector's node
// data (Q, B, the pass flags, the normals) and its sums (S and C of the current |L|, Λ, E)
// held in local arrays that the compiler keeps in registers: per node and direction one load
// of the carry and one store (directions outermost, as before, loaded Q, e, the pass flag and
// S and stored S at every update, and passed over the tile once more per |L| for Λ).  A vector
// takes the surface form for direction b where one of its nodes has a normal, is a SURFACE
// node or is blocked for b, else the fog-only form (the same for a fog node, whose blocking
// bits and normal are 0).  Λ = Q Σ_d w_d + Σ_k [a2_k S_k + a1_k (B − Q) C_k] per |L| run k
// (``unit``'s regrouping).
template <typename T, bool ATT, bool SURF, bool FL>
void block_tile(const Dims& g, const Args<T>& a, const T* Qf, const T* Bf, const int32_t* dirs,
                int64_t nd, T* const* src, T* const* dst, int64_t p, int64_t u0, int64_t u1,
                bool keep, const SurfVecs<T>& sv, T* lam, T* irr,
                std::vector<T>& work) {
  const int64_t M = g.M, nu = g.nu, nv = g.nv, PV = nv + 2 * M;
  const int64_t rows = u1 - u0, n = rows * nv, off = (p * nu + u0) * nv;
  const T* Q = Qf + off;
  const T* B = Bf + off;
  const T* tau = a.tau + off;
  using W = Word<T>;
  const int64_t NW = blocking_words<T>(g.D);
  constexpr int64_t VW = SurfVecs<T>::VW;
  // the block's runs of equal |L|: [run[k], run[k + 1])
  int64_t run[BLOCK_MAX + 1];
  int64_t nr = 0;
  for (int64_t b = 0; b < nd; ++b)
    if (run_begins(a.kidx, dirs, b)) run[nr++] = b;
  run[nr] = nd;
  T wsum = T(0);
  for (int64_t b = 0; b < nd; ++b) wsum += a.weight[dirs[b]];
  // scratch per run: e = e^{-τ|L|} − 1, a2 = (1 − e^{−2τ|L|})/(2τ|L|), a1 = (1 − e^{−τ|L|})/(τ|L|)
  // (with surfaces); the pass flag in words as wide as T
  const bool sums = keep && ATT && FL;
  const int64_t ne = ATT ? nr : 0, na2 = sums ? nr : 0, na1 = sums && SURF ? nr : 0;
  work.resize(size_t((ne + na2 + na1 + (sums ? 1 : 0) + 1) * n));
  T* e = work.data();
  T* a2 = e + ne * n;
  T* a1 = a2 + na2 * n;
  T* inv = a1 + na1 * n;  // 1/τ (one division per node, not two per node and |L|)
  W* passw = reinterpret_cast<W*>(inv + (sums ? n : 0));
  if (sums) {
#pragma omp simd
    for (int64_t j = 0; j < n; ++j) inv[j] = T(1) / (tau[j] > T(0) ? tau[j] : T(1));
  }
  for (int64_t k = 0; k < ne; ++k) {
    const T len = a.length_k[a.kidx[dirs[run[k]]]];
    T* ek = e + k * n;
#pragma omp simd
    for (int64_t j = 0; j < n; ++j) ek[j] = em1(-(tau[j] * len));
    if (!sums) continue;
    // ``avg`` with 1/τ for the division (t = τ|L|, x = e^{−t} − 1)
    const T il = T(1) / len;
    T* a2k = a2 + k * n;
#pragma omp simd
    for (int64_t j = 0; j < n; ++j) {
      const T x = ek[j];
      a2k[j] = avg_or_series(T(2) * (tau[j] * len), -(x * (x + T(2)) * inv[j] * (T(0.5) * il)));
    }
    if (!SURF) continue;
    T* a1k = a1 + k * n;
#pragma omp simd
    for (int64_t j = 0; j < n; ++j) a1k[j] = avg_or_series(tau[j] * len, -(ek[j] * inv[j] * il));
  }
  {  // (| rather than ||: a branch-free loop that vectorises)
    const uint8_t* fr = a.free + off;
    const uint8_t* su = a.surf + off;
#pragma omp simd
    for (int64_t j = 0; j < n; ++j) passw[j] = W((fr[j] | (SURF ? su[j] : uint8_t(0))) != 0);
  }
  const int64_t nvec = nv / VW, nch = nvec + 1;
  const int64_t vbase = (p * nu + u0) * nch;  // the tile's first row vector (records)
  T* lo = lam + off;
  T* io = irr + off;
  // the block's directions' constants (per tile, not per vector): weight, unit vector, the byte
  // and bit of ``any`` and the word and bit of the records' blocking words; and per row their
  // carries' rows (the arriving rays shifted by (p, q))
  T wt[BLOCK_MAX], uxv[BLOCK_MAX], uyv[BLOCK_MAX], uzv[BLOCK_MAX];
  int64_t kwv[BLOCK_MAX], dwv[BLOCK_MAX];
  uint8_t kbv[BLOCK_MAX];
  int dbv[BLOCK_MAX];
  const T* rsr[BLOCK_MAX];
  T* rdr[BLOCK_MAX];
  for (int64_t b = 0; b < nd; ++b) {
    const int64_t d = dirs[b];
    wt[b] = a.weight[d];
    uxv[b] = a.unit[3 * d];
    uyv[b] = a.unit[3 * d + 1];
    uzv[b] = a.unit[3 * d + 2];
    kwv[b] = d >> 3;
    kbv[b] = uint8_t(1u << (d & 7));
    dwv[b] = (d / WB<T>) * VW;
    dbv[b] = int(d % WB<T>);
  }
  // the nl (≤ VW) nodes from v0 of row r (FULL: nl = VW, known to the compiler)
  auto vec = [&](auto full, int64_t r, int64_t c) __attribute__((always_inline)) {
    constexpr bool FULL = decltype(full)::value;
    const int64_t v0 = c * VW, nl = FULL ? VW : nv - v0, o = r * nv + v0;
    // the vector's record (with surfaces)
    SurfRec<T> rec{false, nullptr, nullptr, nullptr};
    const bool pt = SURF && sv.find(vbase + r * nch + c, rec);
    const bool touch = rec.touch;
    const uint8_t* any = rec.any;  // its blocking bits' OR over the lanes, by byte
    const W* bits = rec.bits;      // its blocking words
    alignas(64) T qv[VW], bv[VW], n0[VW], n1[VW], n2[VW], lv[VW], ev[VW];
    alignas(64) W pv[VW];
    for (int64_t l = 0; l < VW; ++l) {
      const bool in = l < nl;
      qv[l] = in ? Q[o + l] : T(0);
      pv[l] = in ? passw[o + l] : W(0);
      bv[l] = SURF && in ? B[o + l] : T(0);
      lv[l] = T(0);
      ev[l] = T(0);
    }
    if (SURF && pt) {
      const T* nn = rec.normal;
      for (int64_t l = 0; l < VW; ++l) {
        n0[l] = nn[l];
        n1[l] = nn[VW + l];
        n2[l] = nn[2 * VW + l];
      }
    }
    for (int64_t k = 0; k < nr; ++k) {
      alignas(64) T xv[VW], s[VW], cc[VW];
      for (int64_t l = 0; l < VW; ++l) {
        xv[l] = ATT && l < nl ? e[k * n + o + l] : T(0);
        s[l] = T(0);
        cc[l] = T(0);
      }
      for (int64_t b = run[k]; b < run[k + 1]; ++b) {
        const T w = wt[b];
        const T* rs = rsr[b] + v0;
        T* rd = rdr[b] + v0;
        if (SURF && pt && (touch || (any[kwv[b]] & kbv[b]))) {
          const T ux = uxv[b], uy = uyv[b], uz = uzv[b];
          const W* bw = bits + dwv[b];
          const int db = dbv[b];
#pragma omp simd
          for (int64_t l = 0; l < nl; ++l) {
            const T cosw = std::max(-(n0[l] * ux + n1[l] * uy + n2[l] * uz), T(0)) * w;
            rd[l] = step_surf<T, ATT, FL>(rs[l], qv[l], bv[l], xv[l], ((bw[l] >> db) & 1) != 0,
                                          cosw, w, pv[l] != 0, s[l], cc[l], ev[l]);
          }
        } else {
#pragma omp simd
          for (int64_t l = 0; l < nl; ++l)
            rd[l] = step_fog<T, ATT, FL>(rs[l], qv[l], xv[l], w, pv[l] != 0, s[l]);
        }
      }
      if (!(keep && FL)) continue;
      if (ATT) {
        const T* a2k = a2 + k * n + o;
        const T* a1k = a1 + k * n + o;
#pragma omp simd
        for (int64_t l = 0; l < nl; ++l) {
          T t = a2k[l] * s[l];
          if (SURF) t += cc[l] != T(0) ? a1k[l] * (bv[l] - qv[l]) * cc[l] : T(0);
          lv[l] += t;
        }
      } else {
#pragma omp simd
        for (int64_t l = 0; l < nl; ++l) lv[l] += s[l];
      }
    }
    if (keep && FL) {
#pragma omp simd
      for (int64_t l = 0; l < nl; ++l) lo[o + l] += (ATT ? qv[l] * wsum : T(0)) + lv[l];
    }
    if (keep && SURF) {
#pragma omp simd
      for (int64_t l = 0; l < nl; ++l) io[o + l] += ev[l];
    }
  };
  for (int64_t r = 0; r < rows; ++r) {
    for (int64_t b = 0; b < nd; ++b) {
      const int64_t d = dirs[b];
      rsr[b] = src[b] + (u0 + r + a.start[2 * d]) * PV + a.start[2 * d + 1];
      rdr[b] = dst[b] + (u0 + r + M) * PV + M;
    }
    for (int64_t c = 0; c < nvec; ++c) vec(std::true_type{}, r, c);
    if (nvec * VW < nv) vec(std::false_type{}, r, nvec);
  }
}

template <typename T>
using BlockFn = void (*)(const Dims&, const Args<T>&, const T*, const T*, const int32_t*, int64_t,
                         T* const*, T* const*, int64_t, int64_t, int64_t, bool,
                         const SurfVecs<T>&, T*, T*, std::vector<T>&);

template <typename T>
BlockFn<T> pick_block(bool att, bool surf, bool fl) {
  const int key = (att ? 4 : 0) | (surf ? 2 : 0) | (fl ? 1 : 0);
  switch (key) {
    case 0: return block_tile<T, false, false, false>;
    case 1: return block_tile<T, false, false, true>;
    case 2: return block_tile<T, false, true, false>;
    case 3: return block_tile<T, false, true, true>;
    case 4: return block_tile<T, true, false, false>;
    case 5: return block_tile<T, true, false, true>;
    case 6: return block_tile<T, true, true, false>;
    default: return block_tile<T, true, true, true>;
  }
}

// What a run of equal |L| costs a block beyond its directions, in directions: its tables
// (e, a2, a1 per node) and its sums per vector (fog-balls N = 128, M = 5, stop 73: a block of
// 30 directions in 8 runs 46 ms, in 5 runs 38.5 ms: 2.5 ms a run, 0.87 ms a direction)
constexpr double RUN_COST = 3.0;

// The blocks' bounds in ``order`` (the directions by |L|): block j is [cut[j], cut[j + 1]).
// Each cut falls where a run of equal |L| begins (a run cut in two costs both blocks its
// tables), nearest to an equal share of the cost (a direction 1, a run RUN_COST more), no
// block above ``cap`` directions; where no run begins within reach, the equal split's.
inline std::vector<int64_t> block_cuts(const std::vector<int32_t>& order, const int32_t* kidx,
                                       int64_t D, int64_t nblocks, int64_t cap,
                                       std::vector<double>* block_cost) {
  auto starts = [&](int64_t i) { return run_begins(kidx, order.data(), i); };
  std::vector<double> cost(size_t(D + 1), 0.0);  // of order[0, i)
  for (int64_t i = 0; i < D; ++i)
    cost[size_t(i + 1)] = cost[size_t(i)] + 1.0 + (starts(i) ? RUN_COST : 0.0);
  std::vector<int64_t> cut(size_t(nblocks + 1), D);
  cut[0] = 0;
  for (int64_t j = 1; j < nblocks; ++j) {
    const int64_t prev = cut[size_t(j - 1)], left = nblocks - j;
    const int64_t lo = std::max(prev + 1, D - cap * left), hi = std::min(prev + cap, D - left);
    const double target = cost[size_t(D)] * double(j) / double(nblocks);
    int64_t best = -1;
    for (int64_t i = lo; i <= hi; ++i)
      if (starts(i) && (best < 0 || std::fabs(cost[size_t(i)] - target) <
                                        std::fabs(cost[size_t(best)] - target)))
        best = i;
    cut[size_t(j)] = best >= 0 ? best : std::min(hi, std::max(lo, D * j / nblocks));
  }
  block_cost->resize(size_t(nblocks));
  for (int64_t j = 0; j < nblocks; ++j)
    (*block_cost)[size_t(j)] = cost[size_t(cut[size_t(j + 1)])] - cost[size_t(cut[size_t(j)])];
  return cut;
}

// Which thread sweeps each block: the costliest first, each to the thread with the least so
// far (the lowest-numbered of equals), so that the threads' shares are near equal and the
// same at every call (each thread sums its blocks' Λ in block order: the same bits).
inline std::vector<int64_t> block_owners(const std::vector<double>& cost, int64_t nth) {
  const int64_t n = int64_t(cost.size());
  std::vector<int64_t> by(static_cast<size_t>(n)), owner(static_cast<size_t>(n), 0);
  for (int64_t j = 0; j < n; ++j) by[size_t(j)] = j;
  std::stable_sort(by.begin(), by.end(),
                   [&](int64_t x, int64_t y) { return cost[size_t(x)] > cost[size_t(y)]; });
  std::vector<double> load(size_t(nth), 0.0);
  for (int64_t j : by) {
    const int64_t t = std::min_element(load.begin(), load.end()) - load.begin();
    owner[size_t(j)] = t;
    load[size_t(t)] += cost[size_t(j)];
  }
  return owner;
}

template <typename T>
void sweep_blocked(const Dims& g, const Args<T>& a) {
  const int64_t M = g.M, nu = g.nu, nv = g.nv, PU = nu + 2 * M, PV = nv + 2 * M;
  const int64_t plane = PU * PV, nface = g.nw * nu * nv;
  // the directions by |L| (kidx), cut into blocks within the carries' budget, as many blocks
  // as a multiple of the threads, of nearly equal cost (``block_cuts``)
  std::vector<int32_t> order(static_cast<size_t>(g.D));
  for (int64_t d = 0; d < g.D; ++d) order[size_t(d)] = int32_t(d);
  std::stable_sort(order.begin(), order.end(),
                   [&](int32_t x, int32_t y) { return a.kidx[x] < a.kidx[y]; });
  const int64_t cap = std::max<int64_t>(
      1, std::min<int64_t>(BLOCK_MAX, BLOCK_CARRY_BYTES / (2 * plane * int64_t(sizeof(T)))));
  const int64_t want = std::max<int64_t>(1, std::min<int64_t>(g.threads, g.D));
  int64_t nblocks = (g.D + cap - 1) / cap;
  nblocks = std::min<int64_t>(g.D, (nblocks + want - 1) / want * want);
  const int64_t nth = std::min<int64_t>(want, nblocks);
  std::vector<double> block_cost;
  const std::vector<int64_t> cut = block_cuts(order, a.kidx, g.D, nblocks, cap, &block_cost);
  const std::vector<int64_t> owner = block_owners(block_cost, nth);
  const int64_t tile = std::max<int64_t>(
      1, std::min<int64_t>(nu, BLOCK_TILE_BYTES / (6 * nv * int64_t(sizeof(T)))));
  auto run = [&](auto&& body) {
    std::vector<std::thread> pool;
    for (int64_t t = 1; t < nth; ++t) pool.emplace_back(body, t);
    body(int64_t(0));
    for (auto& th : pool) th.join();
  };
  // the face frame's Q and B (gathered from the world frame), the surfaces' records
  std::unique_ptr<T[]> qb(g.world ? new T[size_t(2 * nface)] : nullptr);
  const T* Qf = g.world ? qb.get() : a.Q;
  const T* Bf = g.world ? qb.get() + nface : a.B;
  SurfVecs<T> sv;
  sv.nch = nv / SurfVecs<T>::VW + 1;
  sv.nb = g.nb;
  sv.NW = blocking_words<T>(g.D);
  // the plan's records where it made them (float32's layout; from stop 73: fog-balls N = 128,
  // M = 5 17-20 ms a face on each thread when made here, 15% of an iteration), else here
  const bool planned = g.surfaces && a.rec_index && std::is_same<T, float>::value;
  if (planned) {
    sv.ext_index = a.rec_index;
    sv.ext_touch = a.rec_touch;
    sv.ext_any = a.rec_any;
    sv.ext_bits = reinterpret_cast<const Word<T>*>(a.rec_bits);
    sv.ext_normal = reinterpret_cast<const T*>(a.rec_normal);
  } else if (g.surfaces) {
    sv.index.resize(size_t(g.nw * nu * sv.nch));
    sv.parts.resize(size_t(nth));
  }
  run([&](int64_t t) {
    const int64_t p0 = g.nw * t / nth, p1 = g.nw * (t + 1) / nth;
    if (g.surfaces && !planned) surf_records(g, a, p0 * nu, p1 * nu, t, sv);
    if (g.world) {
      permute(g, p0, p1, true, a.Q, qb.get());
      permute(g, p0, p1, true, a.B, qb.get() + nface);
    }
  });
  // Λ and E per thread, face frame (thread 0's in place, unless the world frame's); each block
  // on its owner (``block_owners``, fixed by the directions alone), so that Λ is summed in the
  // same order at every call (blocks taken as threads came free summed it in an order that
  // changed from call to call, and with it the light's last bits: a Jacobian computed twice
  // differed)
  std::vector<std::vector<T>> acc(static_cast<size_t>(nth));
  run([&](int64_t t) {
    T* lam = nullptr;
    T* irr = nullptr;
    auto own = [&]() {
      if (t == 0 && !g.world) {
        lam = a.lam;
        irr = a.irr;
        std::fill(lam, lam + nface, T(0));
        std::fill(irr, irr + nface, T(0));
      } else {
        acc[size_t(t)].assign(size_t(2 * nface), T(0));
        lam = acc[size_t(t)].data();
        irr = lam + nface;
      }
    };
    if (t == 0) own();
    std::vector<T> work;
    T* src[BLOCK_MAX];
    T* dst[BLOCK_MAX];
    for (int64_t j = 0; j < nblocks; ++j) {
      if (owner[size_t(j)] != t) continue;
      if (!lam) own();
      const int64_t first = cut[size_t(j)];
      const int32_t* dirs = order.data() + first;
      const int64_t nb = cut[size_t(j + 1)] - first;
      for (int64_t m = 0; m < M; ++m) {
        for (int64_t b = 0; b < nb; ++b) {  // the block's carries: its directions' in scratch
          src[b] = a.scratch + 2 * (first + b) * plane;
          dst[b] = src[b] + plane;
          initial_direction(g, a, m, dirs[b], src[b]);
          fill_border(g, dst[b], a.bc[dirs[b]]);
        }
        for (int64_t s = 0; s < g.ns; ++s) {
          const int64_t i = s * M + m, p = source(g, i);
          if (p < 0) {  // padding after an open axis's last plane: nothing goes on
            for (int64_t b = 0; b < nb; ++b)
              for (int64_t u = 0; u < nu; ++u) std::fill_n(dst[b] + (u + M) * PV + M, nv, T(0));
          } else {
            const bool in = s >= g.s0 && s < g.s1;
            const BlockFn<T> fn = pick_block<T>(in && g.att_in, g.surfaces, in && g.fl_in);
            const bool keep = kept(g, i);
            for (int64_t u0 = 0; u0 < nu; u0 += tile)
              fn(g, a, Qf, Bf, dirs, nb, src, dst, p, u0, std::min(u0 + tile, nu), keep,
                 sv, lam, irr, work);
            for (int64_t b = 0; b < nb; ++b) wrap_periodic(g, dst[b]);
          }
          for (int64_t b = 0; b < nb; ++b) std::swap(src[b], dst[b]);
        }
        // the radiance leaving the chain's last plane: exit[m, d] (M, D, nu, nv), if asked
        for (int64_t b = 0; b < (a.exit ? nb : 0); ++b)
          for (int64_t u = 0; u < nu; ++u)
            std::memcpy(a.exit + ((m * g.D + dirs[b]) * nu + u) * nv,
                        src[b] + (u + M) * PV + M, size_t(nv) * sizeof(T));
      }
    }
  });
  // the threads' sums (face frame): into thread 0's, then into the world frame
  T* lam0 = g.world ? acc[0].data() : a.lam;
  T* irr0 = g.world ? acc[0].data() + nface : a.irr;
  run([&](int64_t t) {
    // (whole planes per thread: each writes to the world frame the planes it summed)
    const int64_t p0 = g.nw * t / nth, p1 = g.nw * (t + 1) / nth;
    const int64_t j0 = p0 * nu * nv, j1 = p1 * nu * nv;
    for (size_t x = 1; x < acc.size(); ++x) {
      if (acc[x].empty()) continue;
      const T* l = acc[x].data();
#pragma omp simd
      for (int64_t j = j0; j < j1; ++j) {
        lam0[j] += l[j];
        irr0[j] += l[nface + j];
      }
    }
    if (g.world) {
      permute(g, p0, p1, false, lam0, a.lam);
      permute(g, p0, p1, false, irr0, a.irr);
    }
  });
}

// The sweep (the isotropic step scheme's on a large face by blocks instead), one residue m
// of the planes at a time: a ray leaving plane sM + m arrives at (s + 1)M + m, so the M
// residues are independent chains, and one chain's carry (D planes, two buffers of 9 MB at
// N = 128, M = 5) stays in the last-level cache from plane to plane, where the whole slab's
// (46 MB) went to memory and back at every step.
template <typename T>
void sweep(const Dims& g, const Args<T>& a) {
  // the isotropic step scheme: by blocks of directions where the face is large enough, on
  // any number of threads (since stop 72 the blocks are faster on one thread too: N = 40,
  // M = 3 0.025 against 0.030 s per iteration, N = 64, M = 3 0.080 against 0.093, N = 128,
  // M = 3 0.71 against 0.78; at stop 71 the per-plane unit was as fast or faster there)
  if (g.C == 1 && !g.lin && g.D * g.nw * g.nu * g.nv >= BLOCKED_MIN_UPDATES)
    return sweep_blocked(g, a);
  const int64_t M = g.M, PU = g.nu + 2 * M, PV = g.nv + 2 * M;
  const int64_t chain = g.D * PU * PV;
  T* bufs[2] = {a.scratch, a.scratch + chain};
  const int64_t tiles = (g.nu + g.tile - 1) / g.tile;
  const int64_t nthreads = std::max<int64_t>(1, std::min<int64_t>(g.threads, tiles));
  std::vector<std::vector<T>> work(static_cast<size_t>(nthreads));
  std::vector<std::vector<int32_t>> flags(static_cast<size_t>(nthreads));
  for (int64_t m = 0; m < M; ++m) {
    initial(g, a, m, bufs[0]);
    std::memcpy(bufs[1], bufs[0], size_t(chain) * sizeof(T));
    for (int64_t s = 0; s < g.ns; ++s) {
      const int64_t i = s * M + m, p = source(g, i);
      const T* src = bufs[s % 2];
      T* dst = bufs[1 - s % 2];
      if (p < 0) {  // padding after an open axis's last plane: nothing goes on
        for (int64_t d = 0; d < g.D; ++d)
          for (int64_t u = 0; u < g.nu; ++u)
            std::fill_n(dst + (d * PU + u + M) * PV + M, g.nv, T(0));
        continue;
      }
      const bool in = s >= g.s0 && s < g.s1;
      const bool att = in && g.att_in, fl = in && g.fl_in;
      const UnitFn<T> fn = (g.C > 1 || g.lin) ? pick_general<T>(att, g.surfaces, fl, g.lin)
                                              : pick<T>(att, g.surfaces, fl);
      std::atomic<int64_t> next{0};
      auto worker = [&](int64_t t) {
        for (int64_t j = next++; j < tiles; j = next++) {
          const int64_t u0 = j * g.tile;
          fn(g, a, src, dst, i, p, u0, std::min(u0 + g.tile, g.nu), work[size_t(t)],
             flags[size_t(t)]);
        }
      };
      std::vector<std::thread> pool;
      for (int64_t t = 1; t < nthreads; ++t) pool.emplace_back(worker, t);
      worker(0);
      for (auto& th : pool) th.join();
      for (int64_t d = 0; d < g.D; ++d) wrap_periodic(g, dst + d * PU * PV);
    }
    // the radiance leaving the chain's last plane: exit[m, d] (M, D, nu, nv), if asked
    const T* last = bufs[g.ns % 2];
    for (int64_t d = 0; d < (a.exit ? g.D : 0); ++d)
      for (int64_t u = 0; u < g.nu; ++u)
        std::memcpy(a.exit + ((m * g.D + d) * g.nu + u) * g.nv, last + (d * PU + u + M) * PV + M,
                    size_t(g.nv) * sizeof(T));
  }
}


// ---------------------------------------------------------------------------------------------
// The sub-stepped scheme (``_kernel._sweep_face_substep_loop``'s values): each segment
// y − L → y crosses the M − 1 planes between its end nodes, where the ray takes the extinction
// and source of the node nearest to the crossing (``sub``: the window origins of those nodes)
// over one plane's length and deposits its mean radiance in that node's Λ (and the weight of
// the sub-steps whose light is known in a last channel, by which each node's Λ is divided at
// the end).  The chains are visited one residue at a time as in ``sweep``; per arrival plane
// the window of the M planes before it (their solid flags, the crossings' factors per
// distinct |L| and sources, padded: wrapped on periodic sides, 0 elsewhere) is built once,
// the directions are shared among threads, each depositing into its own padded window of
// the M planes its segments reach, and the windows are folded into Λ afterwards.

// The face plane's node data at sweep plane c: -1 before the first plane (the programs'
// zeros: no fog, not solid), -2 for an open axis's padding (no fog, solid), else the face
// plane.
inline int64_t sub_plane(const Dims& g, int64_t c) {
  if (c < 0) return -1;
  const int64_t p = source(g, c);
  return p < 0 ? -2 : p;
}

// Whether sweep plane c's Λ is returned (a kept plane of the ns slabs; not the periodic
// axis's extra slab, whose own planes are the first ones again).
inline bool sub_kept(const Dims& g, int64_t c) {
  return c >= 0 && c < g.ns * g.M && kept(g, c);
}

template <typename T>
struct SubPlane {
  // one sweep plane as the crossings read it, padded (PP each): its solid flags, τ_half, per
  // distinct |L| the crossing's e^{-τ} − 1 and (1 − e^{-τ})/τ (τ = τ_half·2/M·|L|), the source
  // channels (1 + J); ``fog``: whether the plane holds a face plane's fog (else τ = 0, no source);
  // ``live``: per channel, whether it is nonzero anywhere in the plane (a direction's source
  // skips the others: the once-scattered sweep's channels are all 0 but the sun's)
  std::vector<T> solid, tau, em, av, q;
  std::vector<uint8_t> live;
  bool fog = false;
};

template <typename T>
struct SubArrival {
  // the arrival plane (n each): the source channels, B, per distinct |L| the node's own half
  // sub-steps' e^{-τ} − 1, (1 − e^{-2τ})/2τ, (1 − e^{-τ})/τ (τ = τ_half·|L|/M), the SURFACE
  // flag as a number, the normal; bytes: SURFACE, pass, the blocking bytes (nb n)
  std::vector<T> qa, B, eo, a2, a1, sft, nrm;
  std::vector<uint8_t> st, pass, bits, live;
  int64_t p = -1;
};

template <typename T>
void sub_pad(const Dims& g, const T* vals, int64_t stride, T* out) {  // (nu, nv) → (PU, PV)
  const int64_t M = g.M, PV = g.nv + 2 * M, PP = (g.nu + 2 * M) * PV;
  std::fill(out, out + PP, T(0));
  for (int64_t u = 0; u < g.nu; ++u)
    for (int64_t v = 0; v < g.nv; ++v) out[(u + M) * PV + M + v] = vals[(u * g.nv + v) * stride];
  wrap_periodic(g, out);
}

// Sweep plane c's record but its tables (``sub_plane_table``); with ``lam_bar`` (the
// transpose) ``q`` holds the plane's Λ̄ / M (Q's slot, 1 + NK channels) where it is returned,
// else its source channels (1 + J) and which of them are live.
template <typename T>
void sub_plane_fill(const Dims& g, const Args<T>& a, int64_t c, SubPlane<T>& r,
                    bool lam_bar = false) {
  const int64_t M = g.M, n = g.nu * g.nv, CQ = lam_bar ? 1 + g.NK : 1 + g.J;
  const int64_t PP = (g.nu + 2 * M) * (g.nv + 2 * M);
  r.solid.assign(size_t(PP), T(0));
  r.tau.assign(size_t(PP), T(0));
  r.em.resize(size_t(g.K * PP));
  r.av.resize(size_t(g.K * PP));
  r.q.assign(size_t(CQ * PP), T(0));
  r.live.assign(size_t(CQ), 0);
  const int64_t p = sub_plane(g, c);
  r.fog = p >= 0;
  if (p == -1) return;  // before the first plane: the programs' zeros
  std::vector<T> flag(static_cast<size_t>(n), T(1));
  const int64_t off = p * n;
  if (p >= 0)
    for (int64_t j = 0; j < n; ++j) flag[j] = T(!(a.free[off + j] || a.surf[off + j]));
  sub_pad(g, flag.data(), 1, r.solid.data());
  if (!r.fog) return;  // padding: solid, no fog
  sub_pad(g, a.tau + off, 1, r.tau.data());
  if (lam_bar) {
    if (!sub_kept(g, c)) return;  // no Λ̄ there
    std::vector<T> lb(static_cast<size_t>(n));
    for (int64_t ch = 0; ch < CQ; ++ch) {
      for (int64_t j = 0; j < n; ++j) lb[j] = a.Q[(off + j) * CQ + ch] / T(M);
      sub_pad(g, lb.data(), 1, r.q.data() + ch * PP);
    }
    return;
  }
  for (int64_t ch = 0; ch < CQ; ++ch) {
    T* qc = r.q.data() + ch * PP;
    sub_pad(g, a.Q + off * g.C + ch, g.C, qc);
    for (int64_t j = 0; j < PP && !r.live[size_t(ch)]; ++j) r.live[size_t(ch)] = qc[j] != T(0);
  }
}

template <typename T>
void sub_plane_table(const Dims& g, const Args<T>& a, int64_t k, SubPlane<T>& r) {
  const int64_t PP = (g.nu + 2 * g.M) * (g.nv + 2 * g.M);
  T* e = r.em.data() + k * PP;
  T* v = r.av.data() + k * PP;
  if (!r.fog) {
    std::fill(e, e + PP, T(0));
    std::fill(v, v + PP, T(1));
    return;
  }
  const T len = a.length_k[k];
  const T* tp = r.tau.data();
#pragma omp simd
  for (int64_t j = 0; j < PP; ++j) e[j] = em1(-((tp[j] * (T(2) / T(g.M))) * len));
#pragma omp simd
  for (int64_t j = 0; j < PP; ++j) v[j] = avg((tp[j] * (T(2) / T(g.M))) * len, e[j]);
}

// The arrival plane i's record but its tables (``sub_arrival_table``).
template <typename T>
void sub_arrival_fill(const Dims& g, const Args<T>& a, int64_t i, SubArrival<T>& r,
                      bool sources = true) {
  const int64_t n = g.nu * g.nv, C1 = 1 + g.J, K = g.K;
  r.qa.assign(size_t(C1 * n), T(0));
  r.B.assign(size_t(n), T(0));
  r.eo.resize(size_t(K * n));
  r.a2.resize(size_t(K * n));
  r.a1.resize(size_t(K * n));
  r.sft.assign(size_t(n), T(0));
  r.nrm.assign(size_t(3 * n), T(0));
  r.st.assign(size_t(n), 0);
  r.pass.assign(size_t(n), 0);
  r.bits.assign(size_t(g.nb * n), 0);
  r.live.assign(size_t(C1), 0);
  r.p = sub_plane(g, i);
  if (r.p < 0) return;  // padding after an open axis: nothing there
  const int64_t off = r.p * n;
  for (int64_t j = 0; j < n; ++j) {
    for (int64_t c = 0; c < (sources ? C1 : 0); ++c) {
      const T x = a.Q[(off + j) * g.C + c];
      r.qa[c * n + j] = x;
      r.live[size_t(c)] |= uint8_t(x != T(0));
    }
    if (sources) r.B[j] = a.B[off + j];
    const bool s = g.surfaces && a.surf[off + j] != 0;
    r.st[j] = uint8_t(s);
    r.sft[j] = T(s);
    r.pass[j] = uint8_t(a.free[off + j] != 0 || s);
  }
  if (g.surfaces)
    for (int64_t j = 0; j < n; ++j) {
      for (int c = 0; c < 3; ++c) r.nrm[c * n + j] = a.normal[(off + j) * 3 + c];
      for (int64_t b = 0; b < g.nb; ++b) r.bits[b * n + j] = a.bits[(off + j) * g.nb + b];
    }
}

template <typename T>
void sub_arrival_table(const Dims& g, const Args<T>& a, int64_t k, SubArrival<T>& r) {
  const int64_t n = g.nu * g.nv;
  T *e = r.eo.data() + k * n, *x2 = r.a2.data() + k * n, *x1 = r.a1.data() + k * n;
  if (r.p < 0) {
    std::fill(e, e + n, T(0));
    std::fill(x2, x2 + n, T(1));
    std::fill(x1, x1 + n, T(1));
    return;
  }
  const T len = a.length_k[k];
  const T* tau = a.tau + r.p * n;
#pragma omp simd
  for (int64_t j = 0; j < n; ++j) e[j] = em1(-(tau[j] * len / T(g.M)));
#pragma omp simd
  for (int64_t j = 0; j < n; ++j) {
    const T t = tau[j] * len / T(g.M), x = e[j];
    x2[j] = avg(T(2) * t, x * (x + T(2)));
    x1[j] = avg(t, x);
  }
}

// the sub-stepped kernel's per-thread deposit rows of one tile, bytes (half of one core's L2 on
// this project's CPU)
constexpr int64_t SUB_TILE_BYTES = 256 * 1024;

// Rows per tile of the sub-stepped kernels: a thread sweeps every direction over a tile before
// the next, so that its window's rows the tile's segments reach (``channels`` M (tile + 2M) PV
// values) stay in its cache; at least two tiles per thread.
template <typename T>
int64_t sub_tile(const Dims& g, int64_t channels, int64_t nth) {
  const int64_t row_bytes = channels * g.M * (g.nv + 2 * g.M) * int64_t(sizeof(T));
  return std::max<int64_t>(1, std::min<int64_t>(SUB_TILE_BYTES / row_bytes - 2 * g.M,
                                                (g.nu + 2 * nth - 1) / (2 * nth)));
}

// Add window plane ``wp`` (1 … M), channel ``ch`` of every thread's padded window (``channels``
// per plane) into ``dst`` (nu, nv): the margins wrapped on periodic sides, dropped elsewhere.
template <typename T>
void sub_fold(const Dims& g, const std::vector<std::vector<T>>& accs, int64_t channels,
              int64_t wp, int64_t ch, T* dst) {
  const int64_t M = g.M, nu = g.nu, nv = g.nv, PU = nu + 2 * M, PV = nv + 2 * M, PP = PU * PV;
  for (const auto& acc : accs) {
    const T* ap = acc.data() + ((wp - 1) * channels + ch) * PP;
    for (int64_t pu = 0; pu < PU; ++pu) {
      int64_t ru = pu - M;
      if (g.per_u) ru = ((ru % nu) + nu) % nu;
      else if (ru < 0 || ru >= nu) continue;
      const T* row = ap + pu * PV;
      T* lr = dst + ru * nv;
#pragma omp simd
      for (int64_t v = 0; v < nv; ++v) lr[v] += row[M + v];
      if (g.per_v)
        for (int64_t pv = 0; pv < M; ++pv) {
          lr[((pv - M) % nv + nv) % nv] += row[pv];
          lr[(nv + pv) % nv] += row[M + nv + pv];
        }
    }
  }
}

// Add every thread's (n,) array into ``dst``.
template <typename T>
void sub_sum(const std::vector<std::vector<T>>& parts, int64_t n, T* dst) {
  for (const auto& part : parts) {
    const T* x = part.data();
#pragma omp simd
    for (int64_t j = 0; j < n; ++j) dst[j] += x[j];
  }
}

// A barrier for the sweep's threads (``native_common.h``: the waits come three times per plane).
using difffog_native::SpinBarrier;

// One direction's segments arriving at rows [u0, u1) of sweep plane i: the carry moved and
// stepped through the crossings and the node's own halves (FOG), its deposits into the
// thread's window ``acc`` (M planes i − M + 1 … i, 1 + NK channels and the weight, padded) and
// E into ``irr``; without FOG the rays only move (a blocked arrival's and a restart's
// radiosity, E).  ``rows``: five row buffers (nv each).
template <typename T, bool FOG, bool SURF, bool FL, bool ANI>
void sub_direction(const Dims& g, const Args<T>& a, const SubPlane<T>* const* win,
                   const SubArrival<T>& arr, int64_t d, int64_t u0, int64_t u1, const T* src,
                   T* dst, T* acc, T* irr, T* rows) {
  const int64_t M = g.M, nu = g.nu, nv = g.nv, n = nu * nv, PV = nv + 2 * M;
  const int64_t PP = (nu + 2 * M) * PV, NC = 1 + g.NK, D = g.D;
  const int64_t k = a.kidx[d];
  const T w = a.weight[d], invM = T(1) / T(M);
  const T* tab = a.table + d * g.J;
  const int64_t su = a.start[2 * d], sv = a.start[2 * d + 1];
  const T ux = a.unit[3 * d], uy = a.unit[3 * d + 1], uz = a.unit[3 * d + 2];
  const int bit = int(d & 7);
  T *rr = rows, *vr = rows + nv, *qr = rows + 2 * nv, *xr = rows + 3 * nv, *ar = rows + 4 * nv;
  // this direction's Λ channel weights: w, then w Ỹ_c(d) for the NK moments
  T chan[64];
  const int64_t nc = NC < 64 ? NC : 64;
  chan[0] = w;
  for (int64_t c = 1; c < nc; ++c) chan[c] = w * tab[c - 1];
  for (int64_t u = u0; u < u1; ++u) {
    const int64_t o = u * nv;
    const T* rs = src + (d * (nu + 2 * M) + u + su) * PV + sv;
    const T* s0 = win[0]->solid.data() + (u + su) * PV + sv;
    const T* bb = arr.B.data() + o;
    const uint8_t* stp = arr.st.data() + o;
    const T* sft = arr.sft.data() + o;
    const uint8_t* bl = arr.bits.data() + (d >> 3) * n + o;
#pragma omp simd
    for (int64_t v = 0; v < nv; ++v) {
      rr[v] = rs[v];
      vr[v] = T(1) - s0[v];
    }
    if (SURF) {
#pragma omp simd
      for (int64_t v = 0; v < nv; ++v) {
        const bool blk = ((bl[v] >> bit) & 1) != 0;
        rr[v] = blk ? bb[v] : rr[v];
        vr[v] = blk ? T(1) : vr[v];
      }
    }
    for (int64_t j = 1; j < M; ++j) {
      const int64_t cu = a.sub[((j - 1) * D + d) * 2], cv = a.sub[((j - 1) * D + d) * 2 + 1];
      const int64_t base = (u + cu) * PV + cv;
      if (SURF) {  // crossing a solid node: a surface arrival's chain restarts with y's
        // radiosity, any other's light is unknown until it arrives
        const T* sp = win[j]->solid.data() + base;
#pragma omp simd
        for (int64_t v = 0; v < nv; ++v) {
          const bool sj = sp[v] > T(0);
          rr[v] = (sj && stp[v]) ? bb[v] : rr[v];
          vr[v] = sj ? sft[v] : vr[v];
        }
      }
      if (!FOG) continue;
      const T* e = win[j]->em.data() + k * PP + base;
      const T* av = win[j]->av.data() + k * PP + base;
      const T* q0 = win[j]->q.data() + base;
      const T* q = q0;
      if (ANI) {
        std::memcpy(qr, q0, size_t(nv) * sizeof(T));
        const uint8_t* live = win[j]->live.data();
        for (int64_t c = 0; c < g.J; ++c) {
          if (!live[1 + c]) continue;  // 0 everywhere in the plane
          const T tc = tab[c];
          const T* qc = q0 + (1 + c) * PP;
#pragma omp simd
          for (int64_t v = 0; v < nv; ++v) qr[v] += tc * qc[v];
        }
        q = qr;
      }
#pragma omp simd
      for (int64_t v = 0; v < nv; ++v) {
        const T r = rr[v], qv = q[v];
        const T rbar = qv + (r - qv) * av[v];
        rr[v] = r + e[v] * (r - qv);
        xr[v] = vr[v] * rbar;
      }
      if (!FL) continue;
      T* ap = acc + ((j - 1) * (nc + 1)) * PP + base;
      for (int64_t c = 0; c < nc; ++c) {
        const T cw = chan[c];
        T* ac = ap + c * PP;
#pragma omp simd
        for (int64_t v = 0; v < nv; ++v) ac[v] += cw * xr[v] * invM;
      }
      T* aw = ap + nc * PP;
#pragma omp simd
      for (int64_t v = 0; v < nv; ++v) aw[v] += w * vr[v] * invM;
    }
    T* rd = dst + (d * (nu + 2 * M) + u + M) * PV + M;
    const uint8_t* ps = arr.pass.data() + o;
    const T *n0 = arr.nrm.data() + o, *n1 = n0 + n, *n2 = n1 + n;
    T* ai = irr + o;
    if (!FOG) {
#pragma omp simd
      for (int64_t v = 0; v < nv; ++v) {
        const T r = rr[v];
        if (SURF) {
          const T ldotn = n0[v] * ux + n1[v] * uy + n2[v] * uz;
          ai[v] += r * std::max(-ldotn, T(0)) * w;
        }
        rd[v] = ps[v] ? r : T(0);
      }
      continue;
    }
    const T* q4 = arr.qa.data() + o;
    if (ANI) {
      std::memcpy(qr, q4, size_t(nv) * sizeof(T));
      for (int64_t c = 0; c < g.J; ++c) {
        if (!arr.live[size_t(1 + c)]) continue;  // 0 everywhere in the plane
        const T tc = tab[c];
        const T* qc = q4 + (1 + c) * n;
#pragma omp simd
        for (int64_t v = 0; v < nv; ++v) qr[v] += tc * qc[v];
      }
      q4 = qr;
    }
    const T *e = arr.eo.data() + k * n + o, *x2 = arr.a2.data() + k * n + o,
            *x1 = arr.a1.data() + k * n + o;
#pragma omp simd
    for (int64_t v = 0; v < nv; ++v) {
      const T r = rr[v], qv = q4[v], x = e[v];
      T r_arr = r + x * (r - qv);
      T r_avg = qv + (r - qv) * x2[v];
      if (SURF) {
        const bool blk = ((bl[v] >> bit) & 1) != 0;
        r_arr = blk ? bb[v] : r_arr;
        r_avg = blk ? qv + (bb[v] - qv) * x1[v] : r_avg;
        const T ldotn = n0[v] * ux + n1[v] * uy + n2[v] * uz;
        ai[v] += r_arr * std::max(-ldotn, T(0)) * w;
      }
      ar[v] = r_avg;
      rd[v] = ps[v] ? r_arr + x * (r_arr - qv) : T(0);
    }
    if (!FL) continue;
    T* ap = acc + ((M - 1) * (nc + 1)) * PP + (u + M) * PV + M;  // the arrival plane's own
    for (int64_t c = 0; c < nc; ++c) {
      const T cw = chan[c];
      T* ac = ap + c * PP;
#pragma omp simd
      for (int64_t v = 0; v < nv; ++v) ac[v] += cw * ar[v] * invM;
    }
  }
}

template <typename T>
using SubFn = void (*)(const Dims&, const Args<T>&, const SubPlane<T>* const*,
                       const SubArrival<T>&, int64_t, int64_t, int64_t, const T*, T*, T*, T*,
                       T*);

template <typename T, bool ANI>
SubFn<T> sub_pick_(bool fog, bool surf, bool fl) {
  const int key = (fog ? 4 : 0) | (surf ? 2 : 0) | (fl ? 1 : 0);
  switch (key) {
    case 0: case 1: return sub_direction<T, false, false, false, ANI>;
    case 2: case 3: return sub_direction<T, false, true, false, ANI>;
    case 4: return sub_direction<T, true, false, false, ANI>;
    case 5: return sub_direction<T, true, false, true, ANI>;
    case 6: return sub_direction<T, true, true, false, ANI>;
    default: return sub_direction<T, true, true, true, ANI>;
  }
}

// The sub-stepped sweep: Λ (nw, nu, nv[, 1 + NK]) over the sub-steps whose light is known, E
// and the radiance leaving the last M planes, as ``_sweep_face_substep_loop`` returns them.
// The planes are visited in sweep order (arrival i's rays left plane i − M: the carries of
// the last M + 1 planes are kept, and each plane's record is built once, when it joins the
// window of M planes the next arrivals cross).  Per plane, all threads in step: the new
// record's tables shared by distinct |L|, then the directions, then the threads' windows
// folded into Λ shared by (plane, channel).  The directions' work is shared by row tiles, each
// thread sweeping every direction over its tile before the next.
template <typename T>
void substep_sweep(const Dims& g, const Args<T>& a) {
  const int64_t M = g.M, nu = g.nu, nv = g.nv, n = nu * nv, PU = nu + 2 * M, PV = nv + 2 * M;
  const int64_t PP = PU * PV, chain = g.D * PP, NC = 1 + g.NK, K = g.K, total = g.ns * M;
  const int64_t planes = total + (g.per_w && g.att_in ? M : 0);  // a periodic axis: one more
  // slab, whose crossings finish the last slab's Λ
  const bool ani = g.J > 0;
  const size_t nth = static_cast<size_t>(std::max<int64_t>(1, std::min<int64_t>(g.threads, g.D)));
  std::vector<T> carry(static_cast<size_t>((M + 1) * chain));
  auto slot = [&](int64_t c) { return carry.data() + (((c % (M + 1)) + M + 1) % (M + 1)) * chain; };
  for (int64_t c = 0; c <= M; ++c) initial(g, a, 0, carry.data() + c * chain);  // bc borders
  for (int64_t m = 0; m < M; ++m) initial(g, a, m, slot(m - M));  // before the first planes
  // Λ, its moments and the known sub-steps' weight per face plane, channels first
  std::vector<T> lam(static_cast<size_t>(g.nw * (NC + 1) * n), T(0));
  std::fill(a.irr, a.irr + g.nw * n, T(0));
  std::vector<SubPlane<T>> ring(static_cast<size_t>(M));  // plane c in ring[c mod M]
  for (int64_t c = -M; c < 0; ++c) {
    SubPlane<T>& r = ring[size_t(c + M)];
    sub_plane_fill(g, a, c, r);
    for (int64_t k = 0; k < K; ++k) sub_plane_table(g, a, k, r);
  }
  SubArrival<T> arr;
  std::vector<const SubPlane<T>*> win(static_cast<size_t>(M));
  const int64_t wsize = M * (NC + 1) * PP;
  std::vector<std::vector<T>> accs(nth), irrs(nth), rows(nth);
  for (size_t t = 0; t < nth; ++t) {
    accs[t].resize(size_t(wsize));
    irrs[t].resize(size_t(n));
    rows[t].resize(size_t(5 * nv));
  }
  T wsum = T(0);
  for (int64_t d = 0; d < g.D; ++d) wsum += a.weight[d];
  const int64_t tile = sub_tile<T>(g, NC + 1, int64_t(nth));
  const int64_t tiles = (nu + tile - 1) / tile;
  SpinBarrier barrier(static_cast<int64_t>(nth));
  std::atomic<int64_t> next_a{0}, next_c{0};
  bool fog = false, fl = false, extra = false;
  SubFn<T> fn = nullptr;

  auto body = [&](size_t t) {
    for (int64_t i = 0; i < planes; ++i) {
      if (t == 0) {  // the plane's records and switches
        const int64_t s = i / M;
        extra = s == g.ns;
        fog = extra ? true : (s >= g.s0 && s < g.s1);
        fl = fog && g.fl_in;
        fn = ani ? sub_pick_<T, true>(fog, g.surfaces, fl)
                 : sub_pick_<T, false>(fog, g.surfaces, fl);
        if (i >= 1) sub_plane_fill(g, a, i - 1, ring[size_t((i - 1) % M)]);
        sub_arrival_fill(g, a, i, arr);
        for (int64_t w = 0; w < M; ++w) win[size_t(w)] = &ring[size_t(((i - M + w) % M + M) % M)];
        next_a = 0;
        next_c = 0;
      }
      barrier.wait();
      for (int64_t task = next_a++; task < 2 * K; task = next_a++) {
        if (task < K) {
          if (i >= 1) sub_plane_table(g, a, task, ring[size_t((i - 1) % M)]);
        } else if (fog) {
          sub_arrival_table(g, a, task - K, arr);
        }
      }
      barrier.wait();
      T* acc = accs[t].data();
      T* irr = irrs[t].data();
      if (fl) std::fill(acc, acc + wsize, T(0));
      std::fill(irr, irr + n, T(0));
      const T* src = slot(i - M);
      T* dst = slot(i);
      // tile j on thread j mod nth: a node's deposits come from the tiles within M rows, so
      // a thread taking the next free tile would split them among the threads' windows
      // differently from call to call, and their sum's last bits with it
      for (int64_t task = int64_t(t); task < tiles; task += int64_t(nth)) {
        const int64_t u0 = task * tile, u1 = std::min(nu, u0 + tile);
        for (int64_t d = 0; d < g.D; ++d)
          fn(g, a, win.data(), arr, d, u0, u1, src, dst, acc, irr, rows[t].data());
      }
      barrier.wait();
      // the threads' windows folded into Λ (plane i − M + w' for w' = 1 … M, per channel),
      // and E
      const int64_t folds = fl ? M * (NC + 1) : 0, tasks = folds + 1 + g.D;
      for (int64_t task = next_c++; task < tasks; task = next_c++) {
        if (task > folds) {  // the carry's border on periodic sides
          wrap_periodic(g, dst + (task - folds - 1) * PP);
          continue;
        }
        if (task == folds) {
          if (!extra && sub_kept(g, i)) sub_sum(irrs, n, a.irr + source(g, i) * n);
          continue;
        }
        const int64_t wp = 1 + task / (NC + 1), ch = task % (NC + 1), c = i - M + wp;
        if (!sub_kept(g, c) || (extra && wp == M)) continue;
        T* lp = lam.data() + (source(g, c) * (NC + 1) + ch) * n;
        sub_fold(g, accs, NC + 1, wp, ch, lp);
        if (wp == M && ch == NC)  // the node's own two halves: weight Σ_d w_d / M, known
          for (int64_t j = 0; j < n; ++j) lp[j] += wsum / T(M);
      }
      barrier.wait();
      if (t == 0 && i == total - 1)  // the radiance leaving the last M planes: exit[m, d]
        for (int64_t m = 0; m < M; ++m) {
          const T* last = slot(total - M + m);
          for (int64_t d = 0; d < g.D; ++d)
            for (int64_t u = 0; u < nu; ++u)
              std::memcpy(a.exit + ((m * g.D + d) * nu + u) * nv,
                          last + (d * PU + u + M) * PV + M, size_t(nv) * sizeof(T));
        }
    }
  };
  std::vector<std::thread> pool;
  for (size_t t = 1; t < nth; ++t) pool.emplace_back(body, t);
  body(0);
  for (auto& th : pool) th.join();
  // each node's Λ over the sub-steps whose light is known (Σ_d w_d over their weight)
  for (int64_t p = 0; p < g.nw; ++p) {
    const T* lp = lam.data() + p * (NC + 1) * n;
    for (int64_t j = 0; j < n; ++j) {
      const T ws = lp[NC * n + j];
      const T scale = ws > T(0) ? wsum / ws : T(0);
      T* out = a.lam + (p * n + j) * NC;
      for (int64_t ch = 0; ch < NC; ++ch) out[ch] = lp[ch * n + j] * scale;
    }
  }
}

// ---------------------------------------------------------------------------------------------
// The transpose of the sub-stepped sweep's linear map (Q, B) → (Λ, E) at fixed τ and zero
// boundary radiance (a gradient's adjoint light solve): ``_kernel.
// _sweep_face_substep_transposed``'s values.  The planes in reverse sweep order: arrival i
// takes the cotangent of its rays' radiance leaving it (written by arrival i + M at the window
// it read, the periodic margins folded back), replays each direction's chain backwards (the
// node's own halves, then the crossings from the last to the first: each takes its deposit's
// cotangent from the crossed plane's Λ̄ and adds its source's cotangent into the thread's
// window there) and writes the cotangent of the radiance it read into plane i − M's carry at
// that window.  Λ̄ comes scaled by the geometry's weight scale (``FaceGeometry.wscale``).

// arrival i's own data for the transpose: the forward's (``sub_arrival_fill``), and its Λ̄ / M
// (NC channels) and Ē where the plane is returned (0 elsewhere)
template <typename T>
void subt_arrival_fill(const Dims& g, const Args<T>& a, int64_t i, SubArrival<T>& r) {
  sub_arrival_fill(g, a, i, r, false);
  const int64_t n = g.nu * g.nv, NC = 1 + g.NK;
  r.qa.assign(size_t(NC * n), T(0));  // (here: Λ̄ / M, channels first)
  r.B.assign(size_t(n), T(0));        // (here: Ē)
  if (!sub_kept(g, i)) return;
  const int64_t off = source(g, i) * n;
  for (int64_t j = 0; j < n; ++j) {
    for (int64_t c = 0; c < NC; ++c) r.qa[c * n + j] = a.Q[(off + j) * NC + c] / T(g.M);
    r.B[j] = a.B[off + j];
  }
}

// One direction's chains arriving at rows [u0, u1) of plane i, transposed: ``abar`` the
// cotangent of the radiance leaving plane i (folded), ``prev`` plane i − M's (written at the
// window the forward read); the sources' cotangents into the thread's window ``acc`` (M
// planes i − M + 1 … i, 1 + J channels, padded), B̄ into ``bb``.  ``rows``: 2(M − 1) + 1 row
// buffers.
template <typename T, bool FOG, bool SURF>
void subt_direction(const Dims& g, const Args<T>& a, const SubPlane<T>* const* win,
                    const SubArrival<T>& arr, int64_t d, int64_t u0, int64_t u1, const T* abar,
                    T* prev, T* acc, T* bb, T* rows) {
  const int64_t M = g.M, nu = g.nu, nv = g.nv, n = nu * nv, PV = nv + 2 * M;
  const int64_t PP = (nu + 2 * M) * PV, NC = 1 + g.NK, C1 = 1 + g.J, D = g.D;
  const int64_t k = a.kidx[d];
  const T w = a.weight[d];
  const T* tab = a.table + d * g.J;
  const int64_t su = a.start[2 * d], sv = a.start[2 * d + 1];
  const T ux = a.unit[3 * d], uy = a.unit[3 * d + 1], uz = a.unit[3 * d + 2];
  const int bit = int(d & 7);
  T chan[64];
  chan[0] = w;
  for (int64_t c = 1; c < NC; ++c) chan[c] = w * tab[c - 1];
  T* rr = rows;                       // the radiance's cotangent along the row
  T* vals = rows + nv;                // per crossing j = 1 … M − 1: its validity
  T* rest = vals + (M - 1) * nv;      // and whether the chain restarts there
  T* lw = rest + (M - 1) * nv;        // a crossing's Λ̄ summed over the channels
  for (int64_t u = u0; u < u1; ++u) {
    const int64_t o = u * nv;
    const T* s0 = win[0]->solid.data() + (u + su) * PV + sv;
    const uint8_t* stp = arr.st.data() + o;
    const T* sft = arr.sft.data() + o;
    const uint8_t* bl = arr.bits.data() + (d >> 3) * n + o;
    // the chain forwards: its validity at each crossing, its restarts (geometry)
    if (FOG || SURF) {
#pragma omp simd
      for (int64_t v = 0; v < nv; ++v) {
        T val = T(1) - s0[v];
        if (SURF) val = ((bl[v] >> bit) & 1) ? T(1) : val;
        lw[v] = val;
      }
      for (int64_t j = 1; j < M; ++j) {
        const int64_t cu = a.sub[((j - 1) * D + d) * 2], cv = a.sub[((j - 1) * D + d) * 2 + 1];
        const T* sp = win[j]->solid.data() + (u + cu) * PV + cv;
        T* vj = vals + (j - 1) * nv;
        T* rj = rest + (j - 1) * nv;
#pragma omp simd
        for (int64_t v = 0; v < nv; ++v) {
          const bool sj = SURF && sp[v] > T(0);
          rj[v] = (sj && stp[v]) ? T(1) : T(0);
          lw[v] = sj ? sft[v] : lw[v];
          vj[v] = lw[v];
        }
      }
    }
    // backwards: the node's own half sub-steps
    const T* ro = abar + (d * (nu + 2 * M) + u + M) * PV + M;
    const uint8_t* ps = arr.pass.data() + o;
    const T *n0 = arr.nrm.data() + o, *n1 = n0 + n, *n2 = n1 + n;
    const T* et = arr.B.data() + o;
    T* bo = bb + o;
    if (FOG) {
      const T *e = arr.eo.data() + k * n + o, *x2 = arr.a2.data() + k * n + o,
              *x1 = arr.a1.data() + k * n + o;
      T* ap = acc + ((M - 1) * C1) * PP + (u + M) * PV + M;  // the arrival node's Q̄
      // the own sub-steps' Λ̄ summed over the channels (lw), then the node's update, its Q̄
      // kept in lw for the channels beyond the first
      std::fill(lw, lw + nv, T(0));
      for (int64_t c = 0; c < NC; ++c) {
        const T cw = chan[c];
        const T* lc = arr.qa.data() + c * n + o;
#pragma omp simd
        for (int64_t v = 0; v < nv; ++v) lw[v] += cw * lc[v];
      }
#pragma omp simd
      for (int64_t v = 0; v < nv; ++v) {
        const T ravg = lw[v];
        const T rt = ps[v] ? ro[v] : T(0), em = e[v], a2 = x2[v];
        T r_arr = rt + em * rt, q4 = -em * rt, r;
        if (SURF) {
          const bool blk = ((bl[v] >> bit) & 1) != 0;
          const T ldotn = n0[v] * ux + n1[v] * uy + n2[v] * uz;
          r_arr = r_arr + et[v] * std::max(-ldotn, T(0)) * w;
          const T a1 = x1[v];
          bo[v] += blk ? r_arr + a1 * ravg : T(0);
          q4 = q4 + (blk ? (T(1) - a1) * ravg : -em * r_arr + (T(1) - a2) * ravg);
          r = blk ? T(0) : r_arr + em * r_arr + a2 * ravg;
        } else {
          q4 = q4 - em * r_arr + (T(1) - a2) * ravg;
          r = r_arr + em * r_arr + a2 * ravg;
        }
        rr[v] = r;
        ap[v] += q4;
        lw[v] = q4;
      }
      for (int64_t c = 0; c < g.J; ++c) {
        const T tc = tab[c];
        T* aq = ap + (1 + c) * PP;
#pragma omp simd
        for (int64_t v = 0; v < nv; ++v) aq[v] += tc * lw[v];
      }
    } else {
#pragma omp simd
      for (int64_t v = 0; v < nv; ++v) {
        T r = ps[v] ? ro[v] : T(0);
        if (SURF) {
          const T ldotn = n0[v] * ux + n1[v] * uy + n2[v] * uz;
          r = r + et[v] * std::max(-ldotn, T(0)) * w;
        }
        rr[v] = r;
      }
    }
    // the crossings, the last first
    for (int64_t j = M - 1; j >= 1; --j) {
      const int64_t cu = a.sub[((j - 1) * D + d) * 2], cv = a.sub[((j - 1) * D + d) * 2 + 1];
      const int64_t base = (u + cu) * PV + cv;
      if (FOG) {
        const T* e = win[j]->em.data() + k * PP + base;
        const T* av = win[j]->av.data() + k * PP + base;
        const T* vj = vals + (j - 1) * nv;
        const T* lq = win[j]->q.data() + base;
        std::fill(lw, lw + nv, T(0));
        for (int64_t c = 0; c < NC; ++c) {
          const T cw = chan[c];
          const T* lc = lq + c * PP;
#pragma omp simd
          for (int64_t v = 0; v < nv; ++v) lw[v] += cw * lc[v];
        }
        T* ap = acc + ((j - 1) * C1) * PP + base;
#pragma omp simd
        for (int64_t v = 0; v < nv; ++v) {
          const T rho = vj[v] * lw[v], r = rr[v], x = e[v], y = av[v];
          const T qj = (T(1) - y) * rho - x * r;
          rr[v] = r + x * r + y * rho;
          ap[v] += qj;
          lw[v] = qj;
        }
        for (int64_t c = 0; c < g.J; ++c) {
          const T tc = tab[c];
          T* aq = ap + (1 + c) * PP;
#pragma omp simd
          for (int64_t v = 0; v < nv; ++v) aq[v] += tc * lw[v];
        }
      }
      if (SURF) {
        const T* rj = rest + (j - 1) * nv;
#pragma omp simd
        for (int64_t v = 0; v < nv; ++v) {
          bo[v] += rj[v] > T(0) ? rr[v] : T(0);
          rr[v] = rj[v] > T(0) ? T(0) : rr[v];
        }
      }
    }
    T* pd = prev + (d * (nu + 2 * M) + u + su) * PV + sv;
#pragma omp simd
    for (int64_t v = 0; v < nv; ++v) {
      T r = rr[v];
      if (SURF) {
        const bool blk = ((bl[v] >> bit) & 1) != 0;
        bo[v] += blk ? r : T(0);
        r = blk ? T(0) : r;
      }
      pd[v] = r;
    }
  }
}

template <typename T>
using SubTFn = void (*)(const Dims&, const Args<T>&, const SubPlane<T>* const*,
                        const SubArrival<T>&, int64_t, int64_t, int64_t, const T*, T*, T*, T*,
                        T*);

template <typename T>
SubTFn<T> subt_pick(bool fog, bool surf) {
  if (fog) return surf ? subt_direction<T, true, true> : subt_direction<T, true, false>;
  return surf ? subt_direction<T, false, true> : subt_direction<T, false, false>;
}

// Fold a padded plane's margins into its interior on the periodic sides (the transpose of
// ``wrap_periodic``: a margin node's value is added to the interior node it copies).
template <typename T>
void fold_periodic(const Dims& g, T* pl) {
  const int64_t M = g.M, nu = g.nu, nv = g.nv, PU = nu + 2 * M, PV = nv + 2 * M;
  auto at = [&](int64_t i, int64_t n) { return ((i - M) % n + n) % n + M; };
  if (g.per_u)
    for (int64_t pu = 0; pu < PU; ++pu) {
      if (pu >= M && pu < nu + M) continue;
      T* dst = pl + at(pu, nu) * PV;
      const T* src = pl + pu * PV;
      for (int64_t pv = 0; pv < PV; ++pv) dst[pv] += src[pv];
    }
  if (g.per_v)
    for (int64_t pu = M; pu < nu + M; ++pu) {
      T* row = pl + pu * PV;
      for (int64_t pv = 0; pv < PV; ++pv)
        if (pv < M || pv >= nv + M) row[at(pv, nv)] += row[pv];
    }
}

// The transposed sweep: Λ̄ (scaled: Q's slot, (nw, nu, nv[, NC])) and Ē (B's slot) → Q̄
// (``lam``'s slot, (nw, nu, nv[, 1 + J])) and B̄ (``irr``'s slot).
template <typename T>
void substep_transposed(const Dims& g, const Args<T>& a) {
  const int64_t M = g.M, nu = g.nu, nv = g.nv, n = nu * nv, PU = nu + 2 * M, PV = nv + 2 * M;
  const int64_t PP = PU * PV, chain = g.D * PP, C1 = 1 + g.J, K = g.K, total = g.ns * M;
  const int64_t planes = total + (g.per_w && g.att_in ? M : 0);
  const size_t nth = static_cast<size_t>(std::max<int64_t>(1, std::min<int64_t>(g.threads, g.D)));
  std::vector<T> carry(static_cast<size_t>((M + 1) * chain), T(0));
  auto slot = [&](int64_t c) { return carry.data() + (((c % (M + 1)) + M + 1) % (M + 1)) * chain; };
  std::vector<T> qbar(static_cast<size_t>(g.nw * C1 * n), T(0));  // channels first
  std::fill(a.irr, a.irr + g.nw * n, T(0));
  std::vector<SubPlane<T>> ring(static_cast<size_t>(M));  // plane c in ring[c mod M]
  auto ring_at = [&](int64_t c) -> SubPlane<T>& { return ring[size_t(((c % M) + M) % M)]; };
  for (int64_t c = planes - 1 - M; c < planes - 1; ++c) {
    sub_plane_fill(g, a, c, ring_at(c), true);
    for (int64_t k = 0; k < K; ++k) sub_plane_table(g, a, k, ring_at(c));
  }
  SubArrival<T> arr;
  std::vector<const SubPlane<T>*> win(static_cast<size_t>(M));
  const int64_t wsize = M * C1 * PP;
  std::vector<std::vector<T>> accs(nth), bbs(nth), rows(nth);
  for (size_t t = 0; t < nth; ++t) {
    accs[t].resize(size_t(wsize));
    bbs[t].resize(size_t(n));
    rows[t].resize(size_t((2 * M + 1) * nv));
  }
  const int64_t tile = sub_tile<T>(g, C1, int64_t(nth));
  const int64_t tiles = (nu + tile - 1) / tile;
  SpinBarrier barrier(static_cast<int64_t>(nth));
  std::atomic<int64_t> next_a{0}, next_c{0};
  bool fog = false;
  SubTFn<T> fn = nullptr;

  auto body = [&](size_t t) {
    for (int64_t i = planes - 1; i >= 0; --i) {
      if (t == 0) {
        const int64_t s = i / M;
        fog = s == g.ns ? true : (s >= g.s0 && s < g.s1);
        fn = subt_pick<T>(fog, g.surfaces);
        if (i < planes - 1) sub_plane_fill(g, a, i - M, ring_at(i - M), true);
        subt_arrival_fill(g, a, i, arr);
        for (int64_t w = 0; w < M; ++w) win[size_t(w)] = &ring_at(i - M + w);
        next_a = 0;
        next_c = 0;
      }
      barrier.wait();
      // the new record's tables, the arrival's own, the cotangent leaving plane i folded, plane
      // i − M's cleared
      const int64_t ta = 2 * K + 2 * g.D;
      for (int64_t task = next_a++; task < ta; task = next_a++) {
        if (task < K) {
          if (i < planes - 1) sub_plane_table(g, a, task, ring_at(i - M));
        } else if (task < 2 * K) {
          if (fog) sub_arrival_table(g, a, task - K, arr);
        } else if (task < 2 * K + g.D) {
          fold_periodic(g, slot(i) + (task - 2 * K) * PP);
        } else {
          T* pl = slot(i - M) + (task - 2 * K - g.D) * PP;
          std::fill(pl, pl + PP, T(0));
        }
      }
      barrier.wait();
      T* acc = accs[t].data();
      T* bb = bbs[t].data();
      if (fog) std::fill(acc, acc + wsize, T(0));
      std::fill(bb, bb + n, T(0));
      const T* abar = slot(i);
      T* prev = slot(i - M);
      for (int64_t task = int64_t(t); task < tiles; task += int64_t(nth)) {  // (as the sweep)
        const int64_t u0 = task * tile, u1 = std::min(nu, u0 + tile);
        for (int64_t d = 0; d < g.D; ++d)
          fn(g, a, win.data(), arr, d, u0, u1, abar, prev, acc, bb, rows[t].data());
      }
      barrier.wait();
      // the threads' windows folded into Q̄ (plane i − M + w', w' = 1 … M, per channel), B̄
      const int64_t folds = fog ? M * C1 : 0, tasks = folds + 1;
      for (int64_t task = next_c++; task < tasks; task = next_c++) {
        if (task == folds) {
          const int64_t p = sub_plane(g, i);
          if (p >= 0) sub_sum(bbs, n, a.irr + p * n);
          continue;
        }
        const int64_t wp = 1 + task / C1, ch = task % C1, p = sub_plane(g, i - M + wp);
        if (p >= 0)  // (not before the first plane, nor padding)
          sub_fold(g, accs, C1, wp, ch, qbar.data() + (p * C1 + ch) * n);
      }
      barrier.wait();
    }
  };
  std::vector<std::thread> pool;
  for (size_t t = 1; t < nth; ++t) pool.emplace_back(body, t);
  body(0);
  for (auto& th : pool) th.join();
  // a periodic sweep axis: the initial carry was each direction's source of the first slab
  if (g.per_w)
    for (int64_t m = 0; m < M; ++m) {
      T* r0 = slot(m - M);
      const int64_t p = source(g, m);
      for (int64_t d = 0; d < g.D; ++d) {
        T* pl = r0 + d * PP;
        fold_periodic(g, pl);
        const T* tab = a.table + d * g.J;
        for (int64_t u = 0; u < nu; ++u)
          for (int64_t v = 0; v < nv; ++v) {
            const T x = pl[(u + M) * PV + M + v];
            qbar[(p * C1) * n + u * nv + v] += x;
            for (int64_t c = 0; c < g.J; ++c) qbar[(p * C1 + 1 + c) * n + u * nv + v] += tab[c] * x;
          }
      }
    }
  for (int64_t p = 0; p < g.nw; ++p)
    for (int64_t j = 0; j < n; ++j)
      for (int64_t c = 0; c < C1; ++c) a.lam[(p * n + j) * C1 + c] = qbar[(p * C1 + c) * n + j];
}

#if DIFFFOG_PART == 1
template void sweep<float>(const Dims& g, const Args<float>& a);
template void substep_sweep<float>(const Dims& g, const Args<float>& a);
template void substep_transposed<float>(const Dims& g, const Args<float>& a);
#elif DIFFFOG_PART == 2
template void sweep<double>(const Dims& g, const Args<double>& a);
template void substep_sweep<double>(const Dims& g, const Args<double>& a);
template void substep_transposed<double>(const Dims& g, const Args<double>& a);
#elif DIFFFOG_PART == 0
extern template void sweep<float>(const Dims& g, const Args<float>& a);
extern template void sweep<double>(const Dims& g, const Args<double>& a);
extern template void substep_sweep<float>(const Dims& g, const Args<float>& a);
extern template void substep_sweep<double>(const Dims& g, const Args<double>& a);
extern template void substep_transposed<float>(const Dims& g, const Args<float>& a);
extern template void substep_transposed<double>(const Dims& g, const Args<double>& a);
#endif

#if DIFFFOG_PART <= 0
template <typename T>
Args<T> args(ffi::AnyBuffer Q, ffi::AnyBuffer B, ffi::AnyBuffer tau, ffi::AnyBuffer normal,
             ffi::AnyBuffer bits, ffi::AnyBuffer free, ffi::AnyBuffer surf, ffi::AnyBuffer bc,
             ffi::AnyBuffer length_k, ffi::AnyBuffer kidx, ffi::AnyBuffer weight,
             ffi::AnyBuffer unit_, ffi::AnyBuffer start, ffi::AnyBuffer table,
             ffi::AnyBuffer slope, ffi::Result<ffi::AnyBuffer>& lam,
             ffi::Result<ffi::AnyBuffer>& irr, ffi::Result<ffi::AnyBuffer>& exit,
             ffi::Result<ffi::AnyBuffer>& scratch) {
  Args<T> a;
  a.Q = static_cast<const T*>(Q.untyped_data());
  a.B = static_cast<const T*>(B.untyped_data());
  a.tau = static_cast<const T*>(tau.untyped_data());
  a.normal = static_cast<const T*>(normal.untyped_data());
  a.bc = static_cast<const T*>(bc.untyped_data());
  a.length_k = static_cast<const T*>(length_k.untyped_data());
  a.weight = static_cast<const T*>(weight.untyped_data());
  a.unit = static_cast<const T*>(unit_.untyped_data());
  a.table = static_cast<const T*>(table.untyped_data());
  a.slope = static_cast<const T*>(slope.untyped_data());
  a.bits = static_cast<const uint8_t*>(bits.untyped_data());
  a.free = static_cast<const uint8_t*>(free.untyped_data());
  a.surf = static_cast<const uint8_t*>(surf.untyped_data());
  a.kidx = static_cast<const int32_t*>(kidx.untyped_data());
  a.start = static_cast<const int32_t*>(start.untyped_data());
  a.lam = static_cast<T*>(lam->untyped_data());
  a.irr = static_cast<T*>(irr->untyped_data());
  a.exit = static_cast<T*>(exit->untyped_data());
  a.scratch = static_cast<T*>(scratch->untyped_data());
  return a;
}

ffi::Error SweepFaceImpl(ffi::AnyBuffer Q, ffi::AnyBuffer B, ffi::AnyBuffer tau,
                         ffi::AnyBuffer normal, ffi::AnyBuffer bits, ffi::AnyBuffer free,
                         ffi::AnyBuffer surf, ffi::AnyBuffer bc, ffi::AnyBuffer length_k,
                         ffi::AnyBuffer kidx, ffi::AnyBuffer weight, ffi::AnyBuffer unit_,
                         ffi::AnyBuffer start, ffi::AnyBuffer table, ffi::AnyBuffer slope,
                         ffi::AnyBuffer rec_index, ffi::AnyBuffer rec_touch,
                         ffi::AnyBuffer rec_any, ffi::AnyBuffer rec_normal,
                         ffi::AnyBuffer rec_bits, ffi::Result<ffi::AnyBuffer> lam,
                         ffi::Result<ffi::AnyBuffer> irr, ffi::Result<ffi::AnyBuffer> exit,
                         ffi::Result<ffi::AnyBuffer> scratch, int64_t M, int64_t nw, int64_t nu,
                         int64_t nv, int64_t ns, int64_t D, int64_t K, int64_t nb, int64_t s0,
                         int64_t s1, int64_t threads, int64_t tile, int64_t surfaces,
                         int64_t per_w, int64_t per_u, int64_t per_v, int64_t att_in,
                         int64_t fl_in, int64_t C, int64_t J, int64_t NK, int64_t linear,
                         int64_t world, int64_t wb, int64_t sw, int64_t su, int64_t sv,
                         int64_t records) {
  Dims g{M, nw, nu, nv, ns, D, K, nb, s0, s1, threads, tile,
         surfaces != 0, per_w != 0, per_u != 0, per_v != 0, att_in != 0, fl_in != 0,
         C, J, NK, linear != 0, world != 0, wb, sw, su, sv};
  if (M < 1 || nw < 1 || nu < 1 || nv < 1 || ns * M < nw || tile < 1 ||
      D != (2 * M + 1) * (2 * M + 1) || C != 1 + J + (linear ? 3 : 0) || NK > J || NK < 0)
    return ffi::Error::InvalidArgument("difffog_sweep_face: inconsistent dimensions");
  const int64_t nrec = int64_t(rec_touch.element_count());
  if (records && (Q.element_type() != ffi::DataType::F32 ||
                  int64_t(rec_index.element_count()) != nw * nu * (nv / 16 + 1) ||
                  int64_t(rec_any.element_count()) != nrec * nb ||
                  int64_t(rec_normal.element_count()) != nrec * 3 * 16 ||
                  int64_t(rec_bits.element_count()) != nrec * ((D + 31) / 32) * 16 ||
                  nb != (D + 7) / 8))
    return ffi::Error::InvalidArgument("difffog_sweep_face: records of the wrong size");
  // the radiance leaving (``exit``) where asked (an array of its size), else not written
  const bool exits = int64_t(exit->element_count()) == M * D * nu * nv;
  if (Q.element_type() == ffi::DataType::F32) {
    Args<float> a = args<float>(Q, B, tau, normal, bits, free, surf, bc, length_k, kidx, weight,
                                unit_, start, table, slope, lam, irr, exit, scratch);
    if (!exits) a.exit = nullptr;
    if (records) {
      a.rec_index = static_cast<const int32_t*>(rec_index.untyped_data());
      a.rec_touch = static_cast<const uint8_t*>(rec_touch.untyped_data());
      a.rec_any = static_cast<const uint8_t*>(rec_any.untyped_data());
      a.rec_normal = static_cast<const float*>(rec_normal.untyped_data());
      a.rec_bits = static_cast<const uint32_t*>(rec_bits.untyped_data());
    }
    sweep<float>(g, a);
  } else if (Q.element_type() == ffi::DataType::F64) {
    Args<double> a = args<double>(Q, B, tau, normal, bits, free, surf, bc, length_k, kidx,
                                  weight, unit_, start, table, slope, lam, irr, exit, scratch);
    if (!exits) a.exit = nullptr;
    sweep<double>(g, a);
  } else {
    return ffi::Error::InvalidArgument("difffog_sweep_face: float32 or float64 only");
  }
  return ffi::Error::Success();
}

ffi::Error SweepSubstepImpl(ffi::AnyBuffer Q, ffi::AnyBuffer B, ffi::AnyBuffer tau,
                            ffi::AnyBuffer normal, ffi::AnyBuffer bits, ffi::AnyBuffer free,
                            ffi::AnyBuffer surf, ffi::AnyBuffer bc, ffi::AnyBuffer length_k,
                            ffi::AnyBuffer kidx, ffi::AnyBuffer weight, ffi::AnyBuffer unit_,
                            ffi::AnyBuffer start, ffi::AnyBuffer sub, ffi::AnyBuffer table,
                            ffi::Result<ffi::AnyBuffer> lam, ffi::Result<ffi::AnyBuffer> irr,
                            ffi::Result<ffi::AnyBuffer> exit, int64_t M, int64_t nw,
                            int64_t nu, int64_t nv, int64_t ns, int64_t D, int64_t K, int64_t nb,
                            int64_t s0, int64_t s1, int64_t threads, int64_t surfaces,
                            int64_t per_w, int64_t per_u, int64_t per_v, int64_t att_in,
                            int64_t fl_in, int64_t C, int64_t J, int64_t NK) {
  Dims g{M, nw, nu, nv, ns, D, K, nb, s0, s1, threads, 1,
         surfaces != 0, per_w != 0, per_u != 0, per_v != 0, att_in != 0, fl_in != 0,
         C, J, NK, false, false, 0, 0, 0, 0};
  if (M < 2 || nw < 1 || nu < 1 || nv < 1 || ns * M < nw || D != (2 * M + 1) * (2 * M + 1) ||
      C < 1 + J || NK > J || NK < 0 || NK + 1 > 64)
    return ffi::Error::InvalidArgument("difffog_sweep_substep: inconsistent dimensions");
  ffi::Result<ffi::AnyBuffer> none = exit;  // the step kernel's scratch and slope: unused
  auto fill = [&](auto a) {
    a.sub = static_cast<const int32_t*>(sub.untyped_data());
    return a;
  };
  if (Q.element_type() == ffi::DataType::F32) {
    substep_sweep<float>(g, fill(args<float>(Q, B, tau, normal, bits, free, surf, bc, length_k,
                                             kidx, weight, unit_, start, table, table, lam, irr,
                                             exit, none)));
  } else if (Q.element_type() == ffi::DataType::F64) {
    substep_sweep<double>(g, fill(args<double>(Q, B, tau, normal, bits, free, surf, bc,
                                               length_k, kidx, weight, unit_, start, table,
                                               table, lam, irr, exit, none)));
  } else {
    return ffi::Error::InvalidArgument("difffog_sweep_substep: float32 or float64 only");
  }
  return ffi::Error::Success();
}

ffi::Error SweepSubstepTransposedImpl(
    ffi::AnyBuffer lam_bar, ffi::AnyBuffer irr_bar, ffi::AnyBuffer tau, ffi::AnyBuffer normal,
    ffi::AnyBuffer bits, ffi::AnyBuffer free, ffi::AnyBuffer surf, ffi::AnyBuffer length_k,
    ffi::AnyBuffer kidx, ffi::AnyBuffer weight, ffi::AnyBuffer unit_, ffi::AnyBuffer start,
    ffi::AnyBuffer sub, ffi::AnyBuffer table, ffi::Result<ffi::AnyBuffer> q_bar,
    ffi::Result<ffi::AnyBuffer> b_bar, int64_t M, int64_t nw, int64_t nu, int64_t nv,
    int64_t ns, int64_t D, int64_t K, int64_t nb, int64_t s0, int64_t s1, int64_t threads,
    int64_t surfaces, int64_t per_w, int64_t per_u, int64_t per_v, int64_t att_in, int64_t J,
    int64_t NK) {
  Dims g{M, nw, nu, nv, ns, D, K, nb, s0, s1, threads, 1,
         surfaces != 0, per_w != 0, per_u != 0, per_v != 0, att_in != 0, true,
         1 + NK, J, NK, false, false, 0, 0, 0, 0};
  if (M < 2 || nw < 1 || nu < 1 || nv < 1 || ns * M < nw || D != (2 * M + 1) * (2 * M + 1) ||
      NK > J || NK < 0 || NK + 1 > 64)
    return ffi::Error::InvalidArgument("difffog_sweep_substep_t: inconsistent dimensions");
  auto fill = [&](auto a) {
    a.sub = static_cast<const int32_t*>(sub.untyped_data());
    return a;
  };
  // Λ̄ in Q's slot, Ē in B's, Q̄ and B̄ in Λ's and E's (the unused slots: the table)
  if (lam_bar.element_type() == ffi::DataType::F32) {
    substep_transposed<float>(g, fill(args<float>(lam_bar, irr_bar, tau, normal, bits, free, surf,
                                                  table, length_k, kidx, weight, unit_, start,
                                                  table, table, q_bar, b_bar, q_bar, q_bar)));
  } else if (lam_bar.element_type() == ffi::DataType::F64) {
    substep_transposed<double>(g, fill(args<double>(lam_bar, irr_bar, tau, normal, bits, free,
                                                    surf, table, length_k, kidx, weight, unit_,
                                                    start, table, table, q_bar, b_bar, q_bar,
                                                    q_bar)));
  } else {
    return ffi::Error::InvalidArgument("difffog_sweep_substep_t: float32 or float64 only");
  }
  return ffi::Error::Success();
}

#endif  // DIFFFOG_PART <= 0
}  // namespace difffog_sweep

#if DIFFFOG_PART <= 0
using difffog_sweep::SweepFaceImpl;
using difffog_sweep::SweepSubstepImpl;
using difffog_sweep::SweepSubstepTransposedImpl;

XLA_FFI_DEFINE_HANDLER_SYMBOL(DifffogSweepFace, SweepFaceImpl,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::AnyBuffer>()  // Q (nw, nu, nv[, C]) or world
                                  .Arg<ffi::AnyBuffer>()  // B (nw, nu, nv) or world
                                  .Arg<ffi::AnyBuffer>()  // τ_half_unit
                                  .Arg<ffi::AnyBuffer>()  // normal (nw, nu, nv, 3)
                                  .Arg<ffi::AnyBuffer>()  // blocked bytes (nw, nu, nv, nb)
                                  .Arg<ffi::AnyBuffer>()  // free (nw, nu, nv) bool
                                  .Arg<ffi::AnyBuffer>()  // surf (nw, nu, nv) bool
                                  .Arg<ffi::AnyBuffer>()  // bc (D,)
                                  .Arg<ffi::AnyBuffer>()  // distinct |L| (K,)
                                  .Arg<ffi::AnyBuffer>()  // kidx (D,) int32
                                  .Arg<ffi::AnyBuffer>()  // weight (D,)
                                  .Arg<ffi::AnyBuffer>()  // unit (D, 3)
                                  .Arg<ffi::AnyBuffer>()  // start (D, 2) int32
                                  .Arg<ffi::AnyBuffer>()  // table (D, J) (or a dummy)
                                  .Arg<ffi::AnyBuffer>()  // slope (D, 3) (or a dummy)
                                  .Arg<ffi::AnyBuffer>()  // records' index (nw, nu, nv/16 + 1)
                                  .Arg<ffi::AnyBuffer>()  // records' touch (R,) uint8
                                  .Arg<ffi::AnyBuffer>()  // records' any (R, nb) uint8
                                  .Arg<ffi::AnyBuffer>()  // records' normals (R, 3, 16) f32
                                  .Arg<ffi::AnyBuffer>()  // records' words (R, NW, 16) u32
                                  .Ret<ffi::AnyBuffer>()  // Λ (nw, nu, nv[, 1 + NK]) or world
                                  .Ret<ffi::AnyBuffer>()  // E (nw, nu, nv) or world
                                  .Ret<ffi::AnyBuffer>()  // exit (M, D, nu, nv)
                                  .Ret<ffi::AnyBuffer>()  // scratch: two carries (2, D, PU, PV)
                                  .Attr<int64_t>("M")
                                  .Attr<int64_t>("nw")
                                  .Attr<int64_t>("nu")
                                  .Attr<int64_t>("nv")
                                  .Attr<int64_t>("ns")
                                  .Attr<int64_t>("D")
                                  .Attr<int64_t>("K")
                                  .Attr<int64_t>("nb")
                                  .Attr<int64_t>("s0")
                                  .Attr<int64_t>("s1")
                                  .Attr<int64_t>("threads")
                                  .Attr<int64_t>("tile")
                                  .Attr<int64_t>("surfaces")
                                  .Attr<int64_t>("per_w")
                                  .Attr<int64_t>("per_u")
                                  .Attr<int64_t>("per_v")
                                  .Attr<int64_t>("att_in")
                                  .Attr<int64_t>("fl_in")
                                  .Attr<int64_t>("C")
                                  .Attr<int64_t>("J")
                                  .Attr<int64_t>("NK")
                                  .Attr<int64_t>("linear")
                                  .Attr<int64_t>("world")  // Q, B, Λ, E in the world frame
                                  .Attr<int64_t>("wb")
                                  .Attr<int64_t>("sw")
                                  .Attr<int64_t>("su")
                                  .Attr<int64_t>("sv")
                                  .Attr<int64_t>("records"));

XLA_FFI_DEFINE_HANDLER_SYMBOL(DifffogSweepSubstep, SweepSubstepImpl,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::AnyBuffer>()  // Q (nw, nu, nv[, C])
                                  .Arg<ffi::AnyBuffer>()  // B (nw, nu, nv)
                                  .Arg<ffi::AnyBuffer>()  // τ_half_unit (the node's own)
                                  .Arg<ffi::AnyBuffer>()  // normal (nw, nu, nv, 3)
                                  .Arg<ffi::AnyBuffer>()  // blocked bytes (nw, nu, nv, nb)
                                  .Arg<ffi::AnyBuffer>()  // free (nw, nu, nv) bool
                                  .Arg<ffi::AnyBuffer>()  // surf (nw, nu, nv) bool
                                  .Arg<ffi::AnyBuffer>()  // bc (D,)
                                  .Arg<ffi::AnyBuffer>()  // distinct |L| (K,)
                                  .Arg<ffi::AnyBuffer>()  // kidx (D,) int32
                                  .Arg<ffi::AnyBuffer>()  // weight (D,)
                                  .Arg<ffi::AnyBuffer>()  // unit (D, 3)
                                  .Arg<ffi::AnyBuffer>()  // start (D, 2) int32
                                  .Arg<ffi::AnyBuffer>()  // crossings' origins (M − 1, D, 2)
                                  .Arg<ffi::AnyBuffer>()  // table (D, J) (or a dummy)
                                  .Ret<ffi::AnyBuffer>()  // Λ (nw, nu, nv[, 1 + NK])
                                  .Ret<ffi::AnyBuffer>()  // E (nw, nu, nv)
                                  .Ret<ffi::AnyBuffer>()  // exit (M, D, nu, nv)
                                  .Attr<int64_t>("M")
                                  .Attr<int64_t>("nw")
                                  .Attr<int64_t>("nu")
                                  .Attr<int64_t>("nv")
                                  .Attr<int64_t>("ns")
                                  .Attr<int64_t>("D")
                                  .Attr<int64_t>("K")
                                  .Attr<int64_t>("nb")
                                  .Attr<int64_t>("s0")
                                  .Attr<int64_t>("s1")
                                  .Attr<int64_t>("threads")
                                  .Attr<int64_t>("surfaces")
                                  .Attr<int64_t>("per_w")
                                  .Attr<int64_t>("per_u")
                                  .Attr<int64_t>("per_v")
                                  .Attr<int64_t>("att_in")
                                  .Attr<int64_t>("fl_in")
                                  .Attr<int64_t>("C")
                                  .Attr<int64_t>("J")
                                  .Attr<int64_t>("NK"));

XLA_FFI_DEFINE_HANDLER_SYMBOL(DifffogSweepSubstepT, SweepSubstepTransposedImpl,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::AnyBuffer>()  // Λ̄ (nw, nu, nv[, 1 + NK]), scaled
                                  .Arg<ffi::AnyBuffer>()  // Ē (nw, nu, nv)
                                  .Arg<ffi::AnyBuffer>()  // τ_half_unit
                                  .Arg<ffi::AnyBuffer>()  // normal (nw, nu, nv, 3)
                                  .Arg<ffi::AnyBuffer>()  // blocked bytes (nw, nu, nv, nb)
                                  .Arg<ffi::AnyBuffer>()  // free (nw, nu, nv) bool
                                  .Arg<ffi::AnyBuffer>()  // surf (nw, nu, nv) bool
                                  .Arg<ffi::AnyBuffer>()  // distinct |L| (K,)
                                  .Arg<ffi::AnyBuffer>()  // kidx (D,) int32
                                  .Arg<ffi::AnyBuffer>()  // weight (D,)
                                  .Arg<ffi::AnyBuffer>()  // unit (D, 3)
                                  .Arg<ffi::AnyBuffer>()  // start (D, 2) int32
                                  .Arg<ffi::AnyBuffer>()  // crossings' origins (M − 1, D, 2)
                                  .Arg<ffi::AnyBuffer>()  // table (D, J) (or a dummy)
                                  .Ret<ffi::AnyBuffer>()  // Q̄ (nw, nu, nv[, 1 + J])
                                  .Ret<ffi::AnyBuffer>()  // B̄ (nw, nu, nv)
                                  .Attr<int64_t>("M")
                                  .Attr<int64_t>("nw")
                                  .Attr<int64_t>("nu")
                                  .Attr<int64_t>("nv")
                                  .Attr<int64_t>("ns")
                                  .Attr<int64_t>("D")
                                  .Attr<int64_t>("K")
                                  .Attr<int64_t>("nb")
                                  .Attr<int64_t>("s0")
                                  .Attr<int64_t>("s1")
                                  .Attr<int64_t>("threads")
                                  .Attr<int64_t>("surfaces")
                                  .Attr<int64_t>("per_w")
                                  .Attr<int64_t>("per_u")
                                  .Attr<int64_t>("per_v")
                                  .Attr<int64_t>("att_in")
                                  .Attr<int64_t>("J")
                                  .Attr<int64_t>("NK"));
#endif  // DIFFFOG_PART <= 0
