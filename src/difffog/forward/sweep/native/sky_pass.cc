// The sky's first collision (``_uncollided.sky_uncollided`` for an open domain) as a CPU
// kernel: for each sky direction ω_k the transmittance T_k from the sky to every node,
// carried sheet by sheet along the axis nearest ω_k (the directions in groups by that axis, as
// ``_sheet_sweep`` sweeps them) with bilinear resampling at the direction's lateral offset per
// sheet, and per node
//
//   fluence    Σ_k w_k T_in,k · (1 − e^{−2τ_k}) / (2τ_k)      (T̄ over the node's segment)
//   irradiance Σ_k w_k T_in,k e^{−τ_k} · max(0, n · ω_k)
//
// with τ_k = σ_t · h / (2 |ω_k,axis|) the node's half segment, T_out = 0 on an opaque node,
// else T_in e^{−2τ_k} (two halves); the sky's 1 enters from outside the lattice; with a
// Henyey–Greenstein fog also the moments Σ_k w_k T̄_k Ỹ(−ω_k), with the linear scheme the
// fluence's change per spacing (``chan``, below).  XLA's program
// for the same arithmetic makes about ten passes over a (directions, sheet) array per sheet
// (slices, pads, products, each its own loop) plus the groups' transposes: fog-balls' 128 sky
// directions took 0.21-0.25 s at N = 64, M = 3 (four light iterations) and 1.7-1.8 s at
// N = 128, M = 5.  Here each row of a sheet, gathered once from the world frame, goes through
// its group's directions, each direction's two sheet buffers (padded with the sky's 1) in the
// core's cache; the group's sums are added onto the earlier groups' in the world frame.
//
// The rows of each sheet are shared among the threads (a fixed partition, a barrier between
// sheets); every node's sums run over the directions in their order on one thread, so the
// result does not depend on the number of threads or on timing.  Values only: derivatives
// are XLA's (``_uncollided._sky_native``'s rule), as for the sweep.
//
// Built with ``sweep_face.cc`` by ``_native.py`` (the same library); registered as the custom
// call "difffog_sky_pass_<hash>" (CPU).
#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <thread>
#include <vector>

#include "native_common.h"
#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace __attribute__((visibility("hidden"))) difffog_sky {

// (``native_common.h``: libmvec's vector exp and expm1 where glibc has them; one barrier wait
// per sheet)
using difffog_native::em1;
using difffog_native::ex;
using difffog_native::SpinBarrier;

// sigma, opaque (nx, ny, nz) and normal (nx, ny, nz, 3) in the world frame (C order); dirs
// (K, 12) per direction, grouped (each group's rows together, in the order its sums are
// added): the sheets' axis and the sign of ω on it, the offset's whole voxels along the two
// other axes (u < v) per sheet, their fractions, the half-segment path h / (2 |ω_axis|), the
// weight and ω (3), a spare column.  flu, irr (nx, ny, nz): the groups' sums, added in order.
// chan (K, NH + 3·slope): per direction the weights of the NH moments (w_k Ỹ(−ω_k)), summed
// with T̄ into mom's first NH channels, and with ``slope`` the three of the fluence's change
// per spacing (−12 w_k |ω_axis| ω_k, world axes), summed with T_in χ(2τ) (the first moment of
// the transmittance over the node's segment, ``_numerics.linear_source_terms``) into the last
// three, 0 on an opaque node; mom (nx, ny, nz, NH + 3·slope).
template <typename T>
T chi(T x) {  // χ(x) = (1/x)∫₀^x e^{−u}(u/x − ½) du: its series below 0.5, else closed
  if (std::abs(x) < T(0.5)) {
    T s = T(0), a = T(1), p = T(1);  // a: (−1)^n/n!, p: x^n
    for (int n = 0; n < 11; ++n) {
      if (n) {
        a = -a / T(n);
        p *= x;
      }
      s += a * T(n) / (T(2) * T(n + 1) * T(n + 2)) * p;
    }
    return s;
  }
  const T em = std::expm1(-x);
  return (((-em) - x * (T(1) + em)) / x + em / T(2)) / x;
}

template <typename T>
void sky_pass(const T* sigma, const uint8_t* opaque, const T* normal, const T* dirs,
              const T* chan, const int64_t* shape, int64_t K, int64_t NH, bool slope,
              int64_t threads, T* flu, T* irr, T* mom) {
  const int64_t n = shape[0] * shape[1] * shape[2];
  const int64_t C = NH + (slope ? 3 : 0);
  std::fill(flu, flu + n, T(0));
  std::fill(irr, irr + n, T(0));
  if (C) std::fill(mom, mom + n * C, T(0));
  const int64_t stride[3] = {shape[1] * shape[2], shape[2], 1};
  constexpr int64_t VL = 64 / sizeof(T);  // rows are computed whole vectors at a time
  for (int64_t k0 = 0; k0 < K;) {
    const int64_t axis = static_cast<int64_t>(dirs[k0 * 12]);
    const bool up = dirs[k0 * 12 + 1] > T(0);  // ω towards +axis: the light enters at the top
    int64_t k1 = k0 + 1;
    while (k1 < K && dirs[k1 * 12] == dirs[k0 * 12] && dirs[k1 * 12 + 1] == dirs[k0 * 12 + 1])
      ++k1;
    const int64_t G = k1 - k0;
    const int64_t ua = axis == 0 ? 1 : 0, va = axis == 2 ? 1 : 2;
    const int64_t S = shape[axis], U = shape[ua], V = shape[va];
    const int64_t ss = stride[axis], su = stride[ua], sv = stride[va];
    int64_t P = 2;  // the buffers' border: every read of a row stays inside (XLA's pad)
    std::vector<int64_t> iu(static_cast<size_t>(G)), iv(static_cast<size_t>(G));
    for (int64_t k = 0; k < G; ++k) {
      iu[size_t(k)] = static_cast<int64_t>(std::floor(dirs[(k0 + k) * 12 + 2]));
      iv[size_t(k)] = static_cast<int64_t>(std::floor(dirs[(k0 + k) * 12 + 3]));
      P = std::max({P, std::abs(iu[size_t(k)]) + 2, std::abs(iv[size_t(k)]) + 2});
    }
    const int64_t Vp = (V + VL - 1) / VL * VL;
    const int64_t PU = U + 2 * P, PV = Vp + 2 * P, plane = PU * PV;
    // two sheet buffers per direction, the sky's 1 to start with (the border stays 1)
    std::vector<T> buf(static_cast<size_t>(2 * G * plane), T(1));
    const int64_t nt = std::max<int64_t>(1, std::min(threads, U));
    SpinBarrier barrier(nt);
    const T* table = dirs + k0 * 12;
    auto work = [&](int64_t t) {
      const int64_t u0 = U * t / nt, u1 = U * (t + 1) / nt;
      // the row's node data (zero past V: no fog, open, no normal), its sums and the
      // transcendental functions of its optical depths, padded to whole vectors
      const auto len = static_cast<size_t>(Vp);
      std::vector<T> f(len), e(len), o(len), sg(len), op(len), n0(len), n1(len), n2(len),
          hv(len), mv(len), xv(len), tv(len), cacc(len * static_cast<size_t>(C));
      for (int64_t s = 0; s < S; ++s) {
        const T* prev_all = buf.data() + (s % 2) * G * plane;
        T* next_all = buf.data() + ((s + 1) % 2) * G * plane;
        const int64_t w = up ? S - 1 - s : s;  // the world's sheet
        for (int64_t u = u0; u < u1; ++u) {
          const int64_t base = w * ss + u * su;
          for (int64_t v = 0; v < Vp; ++v) {
            const bool in = v < V;
            const int64_t i = base + (in ? v : 0) * sv;
            sg[size_t(v)] = in ? sigma[i] : T(0);
            op[size_t(v)] = in && opaque[i] ? T(1) : T(0);
            n0[size_t(v)] = in ? normal[3 * i] : T(0);
            n1[size_t(v)] = in ? normal[3 * i + 1] : T(0);
            n2[size_t(v)] = in ? normal[3 * i + 2] : T(0);
          }
          std::fill(f.begin(), f.end(), T(0));
          std::fill(e.begin(), e.end(), T(0));
          std::fill(cacc.begin(), cacc.end(), T(0));
          for (int64_t k = 0; k < G; ++k) {
            const T* d = table + k * 12;
            const T fu = d[4], fv = d[5], path = d[6], wt = d[7], wx = d[8], wy = d[9],
                    wz = d[10];
            const T* prev = prev_all + k * plane;
            // the rows u + i0 and u + i0 + 1 of the sheet before, from column v + i0 on
            const T* r0 = prev + (u + iu[size_t(k)] + P) * PV + (iv[size_t(k)] + P);
            const T* r1 = r0 + PV;
            T *fp = f.data(), *ep = e.data(), *oo = o.data(), *hp = hv.data(), *mp = mv.data(),
              *tp = tv.data();
            const T *sp = sg.data(), *pp = op.data(), *a0 = n0.data(), *a1 = n1.data(),
                    *a2 = n2.data();
            // the transcendental functions in loops of their own (a vector call clobbers
            // every register: in the loop below it spilled the rest)
#pragma omp simd
            for (int64_t v = 0; v < Vp; ++v) hp[v] = ex(-(sp[v] * path));
            // (1 − e^{−x}) / x, x = 2τ: a series below 1e-3 (``_numerics.one_minus_exp_over``)
#pragma omp simd
            for (int64_t v = 0; v < Vp; ++v) {
              const T x = T(2) * (sp[v] * path);
              const bool small = std::abs(x) < T(1e-3);
              const T xs = small ? T(1) : x;
              mp[v] = small ? T(1) - x / T(2) + x * x / T(6) - x * x * x / T(24)
                            : -em1(-xs) / xs;
            }
#pragma omp simd
            for (int64_t v = 0; v < Vp; ++v) {
              const T a = r0[v] * (T(1) - fu) + r1[v] * fu;
              const T b = r0[v + 1] * (T(1) - fu) + r1[v + 1] * fu;
              const T tin = a * (T(1) - fv) + b * fv;
              tp[v] = tin;
              const T tarr = tin * hp[v];
              oo[v] = pp[v] != T(0) ? T(0) : tarr * hp[v];
              fp[v] += wt * (tin * mp[v]);
              const T c = a0[v] * wx + a1[v] * wy + a2[v] * wz;
              ep[v] += wt * (tarr * std::max(c, T(0)));
            }
            const T* ch = chan + (k0 + k) * C;
            for (int64_t j = 0; j < NH; ++j) {  // the moments: T̄ Ỹ weights
              const T cw = ch[j];
              T* acc = cacc.data() + j * Vp;
#pragma omp simd
              for (int64_t v = 0; v < Vp; ++v) acc[v] += (tp[v] * mp[v]) * cw;
            }
            if (slope) {  // T_in χ(2τ) along the three weights
              T* xp = xv.data();
              for (int64_t v = 0; v < Vp; ++v) xp[v] = tp[v] * chi(T(2) * (sp[v] * path));
              for (int64_t j = 0; j < 3; ++j) {
                const T cw = ch[NH + j];
                T* acc = cacc.data() + (NH + j) * Vp;
#pragma omp simd
                for (int64_t v = 0; v < Vp; ++v) acc[v] += xp[v] * cw;
              }
            }
            std::copy(o.begin(), o.begin() + V, next_all + k * plane + (u + P) * PV + P);
          }
          for (int64_t v = 0; v < V; ++v) {  // this group's sums onto the earlier groups'
            const int64_t i = base + v * sv;
            flu[i] += f[size_t(v)];
            irr[i] += e[size_t(v)];
            for (int64_t j = 0; j < C; ++j) {
              const bool masked = j >= NH && op[size_t(v)] != T(0);  // the slope: 0 if opaque
              mom[i * C + j] += masked ? T(0) : cacc[size_t(j * Vp + v)];
            }
          }
        }
        barrier.wait();  // the next sheet reads rows the other threads wrote
      }
    };
    std::vector<std::thread> pool;
    for (int64_t t = 1; t < nt; ++t) pool.emplace_back(work, t);
    work(0);
    for (auto& th : pool) th.join();
    k0 = k1;
  }
}

ffi::Error SkyPassImpl(ffi::AnyBuffer sigma, ffi::AnyBuffer opaque, ffi::AnyBuffer normal,
                       ffi::AnyBuffer dirs, ffi::AnyBuffer chan, ffi::Result<ffi::AnyBuffer> flu,
                       ffi::Result<ffi::AnyBuffer> irr, ffi::Result<ffi::AnyBuffer> mom,
                       int64_t threads, int64_t nh, int64_t slope) {
  const auto dims = sigma.dimensions();
  const auto dd = dirs.dimensions();
  if (dims.size() != 3 || opaque.dimensions().size() != 3 || normal.dimensions().size() != 4 ||
      dd.size() != 2 || dd[1] != 12 || opaque.element_type() != ffi::DataType::U8 ||
      normal.element_type() != sigma.element_type() || dirs.element_type() != sigma.element_type())
    return ffi::Error::InvalidArgument(
        "difffog_sky_pass: sigma (nx, ny, nz), opaque uint8 (nx, ny, nz), normal (nx, ny, nz, "
        "3), dirs (K, 12), one float type");
  const int64_t shape[3] = {dims[0], dims[1], dims[2]};
  const int64_t K = dd[0];
  const int64_t C = nh + (slope ? 3 : 0);
  if (chan.element_type() != sigma.element_type() ||
      (C && (chan.dimensions().size() != 2 || chan.dimensions()[0] != K ||
             chan.dimensions()[1] != C || mom->dimensions().size() != 4 ||
             mom->dimensions()[3] != C)))
    return ffi::Error::InvalidArgument(
        "difffog_sky_pass: chan (K, nh + 3 slope) and mom (nx, ny, nz, nh + 3 slope)");
  auto run = [&](auto zero) {  // the kernel in the buffers' float type
    using T = decltype(zero);
    sky_pass<T>(static_cast<const T*>(sigma.untyped_data()),
                static_cast<const uint8_t*>(opaque.untyped_data()),
                static_cast<const T*>(normal.untyped_data()),
                static_cast<const T*>(dirs.untyped_data()),
                static_cast<const T*>(chan.untyped_data()), shape, K, nh, slope != 0, threads,
                static_cast<T*>(flu->untyped_data()), static_cast<T*>(irr->untyped_data()),
                static_cast<T*>(mom->untyped_data()));
  };
  if (sigma.element_type() == ffi::DataType::F32)
    run(0.0f);
  else if (sigma.element_type() == ffi::DataType::F64)
    run(0.0);
  else
    return ffi::Error::InvalidArgument("difffog_sky_pass: float32 or float64 only");
  return ffi::Error::Success();
}

}  // namespace difffog_sky

XLA_FFI_DEFINE_HANDLER_SYMBOL(DifffogSkyPass, difffog_sky::SkyPassImpl,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::AnyBuffer>()  // sigma (nx, ny, nz)
                                  .Arg<ffi::AnyBuffer>()  // opaque (nx, ny, nz) uint8
                                  .Arg<ffi::AnyBuffer>()  // normal (nx, ny, nz, 3)
                                  .Arg<ffi::AnyBuffer>()  // dirs (K, 12), grouped
                                  .Arg<ffi::AnyBuffer>()  // chan (K, nh + 3 slope) or (1,)
                                  .Ret<ffi::AnyBuffer>()  // fluence (nx, ny, nz)
                                  .Ret<ffi::AnyBuffer>()  // irradiance (nx, ny, nz)
                                  .Ret<ffi::AnyBuffer>()  // mom (nx, ny, nz, C) or (1,)
                                  .Attr<int64_t>("threads")
                                  .Attr<int64_t>("nh")
                                  .Attr<int64_t>("slope"));
