// The sky's first collision (``_uncollided.sky_uncollided`` for an open domain, isotropic) as a
// CPU kernel: for each sky direction ω_k the transmittance T_k from the sky to every node,
// carried sheet by sheet along the axis nearest ω_k (the directions in groups by that axis, as
// ``_sheet_sweep`` sweeps them) with bilinear resampling at the direction's lateral offset per
// sheet, and per node
//
//   fluence    Σ_k w_k T_in,k · (1 − e^{−2τ_k}) / (2τ_k)      (T̄ over the node's segment)
//   irradiance Σ_k w_k T_in,k e^{−τ_k} · max(0, n · ω_k)
//
// with τ_k = σ_t · h / (2 |ω_k,axis|) the node's half segment, T_out = 0 on an opaque node,
// else T_in e^{−2τ_k} (two halves); the sky's 1 enters from outside the lattice.  XLA's program
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

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

#if defined(__x86_64__) && defined(__GLIBC__) && defined(__GNUC__) && !defined(__clang__) && \
    (__GLIBC__ > 2 || (__GLIBC__ == 2 && __GLIBC_MINOR__ >= 35))
// glibc's libmvec (GLIBC_2.35): vector exp and expm1, declared (GCC's attribute) so that the
// row loops vectorise
extern "C" {
__attribute__((simd("notinbranch"))) float expm1f(float) noexcept;
__attribute__((simd("notinbranch"))) double expm1(double) noexcept;
__attribute__((simd("notinbranch"))) float expf(float) noexcept;
__attribute__((simd("notinbranch"))) double exp(double) noexcept;
}
#endif

namespace __attribute__((visibility("hidden"))) difffog_sky {

inline float em1(float x) { return expm1f(x); }
inline double em1(double x) { return expm1(x); }
inline float ex(float x) { return expf(x); }
inline double ex(double x) { return exp(x); }

struct Barrier {  // a generation count; the threads spin, then yield
  std::atomic<int64_t> gen{0}, arrived{0};
  int64_t n;
  explicit Barrier(int64_t count) : n(count) {}
  void wait() {
    const int64_t g0 = gen.load(std::memory_order_acquire);
    if (arrived.fetch_add(1, std::memory_order_acq_rel) == n - 1) {
      arrived.store(0, std::memory_order_relaxed);
      gen.fetch_add(1, std::memory_order_acq_rel);
      return;
    }
    for (int spins = 0; gen.load(std::memory_order_acquire) == g0; ++spins)
      if (spins > 2000) std::this_thread::yield();
  }
};

// sigma, opaque (nx, ny, nz) and normal (nx, ny, nz, 3) in the world frame (C order); dirs
// (K, 12) per direction, grouped (each group's rows together, in the order its sums are
// added): the sheets' axis and the sign of ω on it, the offset's whole voxels along the two
// other axes (u < v) per sheet, their fractions, the half-segment path h / (2 |ω_axis|), the
// weight and ω (3), a spare column.  flu, irr (nx, ny, nz): the groups' sums, added in order.
template <typename T>
void sky_pass(const T* sigma, const uint8_t* opaque, const T* normal, const T* dirs,
              const int64_t* shape, int64_t K, int64_t threads, T* flu, T* irr) {
  const int64_t n = shape[0] * shape[1] * shape[2];
  std::fill(flu, flu + n, T(0));
  std::fill(irr, irr + n, T(0));
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
    Barrier barrier(nt);
    const T* table = dirs + k0 * 12;
    auto work = [&](int64_t t) {
      const int64_t u0 = U * t / nt, u1 = U * (t + 1) / nt;
      // the row's node data (zero past V: no fog, open, no normal), its sums and the
      // transcendental functions of its optical depths, padded to whole vectors
      const auto len = static_cast<size_t>(Vp);
      std::vector<T> f(len), e(len), o(len), sg(len), op(len), n0(len), n1(len), n2(len),
          hv(len), mv(len);
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
          for (int64_t k = 0; k < G; ++k) {
            const T* d = table + k * 12;
            const T fu = d[4], fv = d[5], path = d[6], wt = d[7], wx = d[8], wy = d[9],
                    wz = d[10];
            const T* prev = prev_all + k * plane;
            // the rows u + i0 and u + i0 + 1 of the sheet before, from column v + i0 on
            const T* r0 = prev + (u + iu[size_t(k)] + P) * PV + (iv[size_t(k)] + P);
            const T* r1 = r0 + PV;
            T *fp = f.data(), *ep = e.data(), *oo = o.data(), *hp = hv.data(), *mp = mv.data();
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
              const T tarr = tin * hp[v];
              oo[v] = pp[v] != T(0) ? T(0) : tarr * hp[v];
              fp[v] += wt * (tin * mp[v]);
              const T c = a0[v] * wx + a1[v] * wy + a2[v] * wz;
              ep[v] += wt * (tarr * std::max(c, T(0)));
            }
            std::copy(o.begin(), o.begin() + V, next_all + k * plane + (u + P) * PV + P);
          }
          for (int64_t v = 0; v < V; ++v) {  // this group's sums onto the earlier groups'
            flu[base + v * sv] += f[size_t(v)];
            irr[base + v * sv] += e[size_t(v)];
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
                       ffi::AnyBuffer dirs, ffi::Result<ffi::AnyBuffer> flu,
                       ffi::Result<ffi::AnyBuffer> irr, int64_t threads) {
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
  const auto* op = static_cast<const uint8_t*>(opaque.untyped_data());
  if (sigma.element_type() == ffi::DataType::F32) {
    sky_pass<float>(static_cast<const float*>(sigma.untyped_data()), op,
                    static_cast<const float*>(normal.untyped_data()),
                    static_cast<const float*>(dirs.untyped_data()), shape, K, threads,
                    static_cast<float*>(flu->untyped_data()),
                    static_cast<float*>(irr->untyped_data()));
  } else if (sigma.element_type() == ffi::DataType::F64) {
    sky_pass<double>(static_cast<const double*>(sigma.untyped_data()), op,
                     static_cast<const double*>(normal.untyped_data()),
                     static_cast<const double*>(dirs.untyped_data()), shape, K, threads,
                     static_cast<double*>(flu->untyped_data()),
                     static_cast<double*>(irr->untyped_data()));
  } else {
    return ffi::Error::InvalidArgument("difffog_sky_pass: float32 or float64 only");
  }
  return ffi::Error::Success();
}

}  // namespace difffog_sky

XLA_FFI_DEFINE_HANDLER_SYMBOL(DifffogSkyPass, difffog_sky::SkyPassImpl,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::AnyBuffer>()  // sigma (nx, ny, nz)
                                  .Arg<ffi::AnyBuffer>()  // opaque (nx, ny, nz) uint8
                                  .Arg<ffi::AnyBuffer>()  // normal (nx, ny, nz, 3)
                                  .Arg<ffi::AnyBuffer>()  // dirs (K, 12), grouped
                                  .Ret<ffi::AnyBuffer>()  // fluence (nx, ny, nz)
                                  .Ret<ffi::AnyBuffer>()  // irradiance (nx, ny, nz)
                                  .Attr<int64_t>("threads"));
