// What the native kernels (``sweep_face.cc``'s sweeps, ``sky_pass.cc``'s sheets) share: glibc's
// vector exp and expm1, and their threads' barrier.
#pragma once

#include <atomic>
#include <cmath>
#include <cstdint>
#include <thread>

#if defined(__x86_64__) && defined(__GLIBC__) && defined(__GNUC__) && !defined(__clang__) && \
    (__GLIBC__ > 2 || (__GLIBC__ == 2 && __GLIBC_MINOR__ >= 35))
// glibc's libmvec has vector exp and expm1 (GLIBC_2.35): declared (GCC's attribute) so that the
// loops that call them vectorise
extern "C" {
__attribute__((simd("notinbranch"))) float expm1f(float) noexcept;
__attribute__((simd("notinbranch"))) double expm1(double) noexcept;
__attribute__((simd("notinbranch"))) float expf(float) noexcept;
__attribute__((simd("notinbranch"))) double exp(double) noexcept;
}
#endif

namespace __attribute__((visibility("hidden"))) difffog_native {

inline float em1(float x) { return expm1f(x); }
inline double em1(double x) { return expm1(x); }
inline float ex(float x) { return expf(x); }
inline double ex(double x) { return exp(x); }

// A generation count; the threads spin, then yield (the waits are short and frequent: three
// per plane in a sweep, one per sheet in the sky pass).
struct SpinBarrier {
  std::atomic<int64_t> gen{0}, arrived{0};
  int64_t n;
  explicit SpinBarrier(int64_t count) : n(count) {}
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

}  // namespace difffog_native
