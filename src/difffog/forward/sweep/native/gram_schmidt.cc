// One Arnoldi step's orthogonalization in ``_krylov.gmres`` as a CPU kernel: classical
// Gram–Schmidt applied twice (CGS2) of a vector a against the live rows [0, live) of the Krylov
// basis V (rows, n):
//
//   h1 = V a,  w = a − h1ᵀV,  h2 = V w,  w ← w − h2ᵀV,  h = h1 + h2,  ‖w‖.
//
// XLA's program for the same products reads every row of V four times whatever ``live`` is (its
// shapes are static): on cloud-plane's default lattice 31 rows of 25 MB, ~135 ms per step on this
// project's 2-core CPU, when a light solve's first cycle has a handful of live rows.  Here each
// of three passes reads only the live rows, in blocks of columns that stay in the core's cache
// between the two products of the middle pass (w's block is formed and dotted with the rows at
// once).  Sums are taken per block in T and accumulated in double, per thread over a fixed
// partition of the blocks, then in thread order: the result does not depend on timing.
//
// Built with ``sweep_face.cc`` by ``_native.py`` (the same library); registered as the custom
// call "difffog_gram_schmidt_<hash>" (CPU).  GMRES is never differentiated through (the implicit
// function's rule solves its own linear systems), so there is no derivative rule.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <thread>
#include <vector>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

// columns per block: up to 41 live rows of 1024 values stay in a core's L2 between the two
// products of the middle pass
constexpr int64_t BLOCK = 1024;

template <typename T>
T dot(const T* x, const T* y, int64_t len) {
  T s = T(0);
#pragma omp simd reduction(+ : s)
  for (int64_t c = 0; c < len; ++c) s += x[c] * y[c];
  return s;
}

// y ← y − Σ_i coef[i]·V[i, c0:c0+len]
template <typename T>
void subtract_rows(const T* V, int64_t n, int64_t live, const double* coef, int64_t c0,
                   int64_t len, T* y) {
  for (int64_t i = 0; i < live; ++i) {
    const T h = T(coef[i]);
    const T* v = V + i * n + c0;
#pragma omp simd
    for (int64_t c = 0; c < len; ++c) y[c] -= h * v[c];
  }
}

template <typename T>
void cgs2(const T* V, const T* a, int64_t n, int64_t rows, int64_t live, int64_t threads, T* w,
          T* h, T* norm) {
  live = std::max<int64_t>(0, std::min(live, rows));
  const int64_t blocks = (n + BLOCK - 1) / BLOCK;
  // a thread per 256 blocks of live row (a thread's start costs more than a small step)
  const int64_t nt = std::max<int64_t>(1, std::min({threads, blocks, blocks * live / 256}));
  std::vector<double> part(static_cast<size_t>(nt * live)), sq(static_cast<size_t>(nt));
  std::vector<double> h1(static_cast<size_t>(live)), h2(static_cast<size_t>(live));
  // pass(t, b0, b1): thread t's blocks [b0, b1), a fixed partition
  auto parallel = [&](auto&& pass) {
    std::fill(part.begin(), part.end(), 0.0);
    std::fill(sq.begin(), sq.end(), 0.0);
    std::vector<std::thread> pool;
    for (int64_t t = 1; t < nt; ++t)
      pool.emplace_back([&, t] { pass(t, blocks * t / nt, blocks * (t + 1) / nt); });
    pass(0, 0, blocks / nt);
    for (auto& th : pool) th.join();
  };
  auto reduce = [&](std::vector<double>& out) {
    for (int64_t i = 0; i < live; ++i) {
      double s = 0.0;
      for (int64_t t = 0; t < nt; ++t) s += part[size_t(t * live + i)];
      out[size_t(i)] = s;
    }
  };
  // pass 1: h1 = V a
  parallel([&](int64_t t, int64_t b0, int64_t b1) {
    double* p = part.data() + t * live;
    for (int64_t b = b0; b < b1; ++b) {
      const int64_t c0 = b * BLOCK, len = std::min(BLOCK, n - c0);
      for (int64_t i = 0; i < live; ++i) p[i] += double(dot(V + i * n + c0, a + c0, len));
    }
  });
  reduce(h1);
  // pass 2: w = a − h1ᵀV and h2 = V w, block by block
  parallel([&](int64_t t, int64_t b0, int64_t b1) {
    double* p = part.data() + t * live;
    for (int64_t b = b0; b < b1; ++b) {
      const int64_t c0 = b * BLOCK, len = std::min(BLOCK, n - c0);
      std::copy(a + c0, a + c0 + len, w + c0);
      subtract_rows(V, n, live, h1.data(), c0, len, w + c0);
      for (int64_t i = 0; i < live; ++i) p[i] += double(dot(V + i * n + c0, w + c0, len));
    }
  });
  reduce(h2);
  // pass 3: w ← w − h2ᵀV and ‖w‖²
  parallel([&](int64_t t, int64_t b0, int64_t b1) {
    for (int64_t b = b0; b < b1; ++b) {
      const int64_t c0 = b * BLOCK, len = std::min(BLOCK, n - c0);
      subtract_rows(V, n, live, h2.data(), c0, len, w + c0);
      sq[size_t(t)] += double(dot(w + c0, w + c0, len));
    }
  });
  double s = 0.0;
  for (int64_t t = 0; t < nt; ++t) s += sq[size_t(t)];
  for (int64_t i = 0; i < rows; ++i) h[i] = i < live ? T(h1[size_t(i)] + h2[size_t(i)]) : T(0);
  *norm = T(std::sqrt(s));
}

ffi::Error GramSchmidtImpl(ffi::AnyBuffer V, ffi::AnyBuffer a, ffi::AnyBuffer live,
                           ffi::Result<ffi::AnyBuffer> w, ffi::Result<ffi::AnyBuffer> h,
                           ffi::Result<ffi::AnyBuffer> norm, int64_t threads) {
  const auto dims = V.dimensions();
  if (dims.size() != 2 || a.dimensions().size() != 1 || a.dimensions()[0] != dims[1] ||
      a.element_type() != V.element_type())
    return ffi::Error::InvalidArgument("difffog_gram_schmidt: V (rows, n) and a (n,) of one type");
  const int64_t rows = dims[0], n = dims[1];
  const int64_t k = *static_cast<const int32_t*>(live.untyped_data());
  if (V.element_type() == ffi::DataType::F32) {
    cgs2<float>(static_cast<const float*>(V.untyped_data()),
                static_cast<const float*>(a.untyped_data()), n, rows, k, threads,
                static_cast<float*>(w->untyped_data()), static_cast<float*>(h->untyped_data()),
                static_cast<float*>(norm->untyped_data()));
  } else if (V.element_type() == ffi::DataType::F64) {
    cgs2<double>(static_cast<const double*>(V.untyped_data()),
                 static_cast<const double*>(a.untyped_data()), n, rows, k, threads,
                 static_cast<double*>(w->untyped_data()), static_cast<double*>(h->untyped_data()),
                 static_cast<double*>(norm->untyped_data()));
  } else {
    return ffi::Error::InvalidArgument("difffog_gram_schmidt: float32 or float64 only");
  }
  return ffi::Error::Success();
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(DifffogGramSchmidt, GramSchmidtImpl,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::AnyBuffer>()  // V (rows, n): the Krylov basis
                                  .Arg<ffi::AnyBuffer>()  // a (n,)
                                  .Arg<ffi::AnyBuffer>()  // live () int32: rows [0, live) count
                                  .Ret<ffi::AnyBuffer>()  // w (n,)
                                  .Ret<ffi::AnyBuffer>()  // h (rows,): 0 beyond live
                                  .Ret<ffi::AnyBuffer>()  // ‖w‖ ()
                                  .Attr<int64_t>("threads"));
