// A barrier for the native kernels' threads (``sweep_face.cc``'s sweeps, ``sky_pass.cc``'s
// sheets): a generation count; they spin, then yield (the waits are short and frequent: three
// per plane in a sweep, one per sheet in the sky pass).
#pragma once

#include <atomic>
#include <cstdint>
#include <thread>

namespace __attribute__((visibility("hidden"))) difffog_native {

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
