// Multiresolution hash-grid encoding, CPU (OpenMP) forward and backward.
//
// Numerically the same function as toolkit.encoding.hash_grid_encode_torch (the reference, also the ONNX
// path): per level l with resolution R_l, the cell corner c0 = min(floor(x * R_l), R_l - 1) (x in [0, 1]),
// f = x * R_l - c0, trilinear weights over the 8 corners; a corner's row is dense
// (cx + cy (R+1) + cz (R+1)^2) when (R+1)^3 <= T, else the sum hash (cx + cy * 2654435761 + cz * 805459861)
// mod T; level l's rows start at l * T.
#include <torch/extension.h>
#include <vector>
#include <cmath>
#include <omp.h>
#include <algorithm>
#include <ATen/Parallel.h>

namespace {

inline void corner_rows(const float* x, int64_t R, int64_t T, bool dense, int64_t level_offset,
                        int64_t rows[8], float weights[8]) {
  int64_t c0[3];
  float f[3];
  for (int d = 0; d < 3; ++d) {
    float p = x[d] * static_cast<float>(R);
    float fl = std::floor(p);
    int64_t c = static_cast<int64_t>(fl);
    if (c > R - 1) c = R - 1;
    if (c < 0) c = 0;
    c0[d] = c;
    f[d] = p - static_cast<float>(c);
  }
  for (int k = 0; k < 8; ++k) {
    int64_t cx = c0[0] + (k & 1), cy = c0[1] + ((k >> 1) & 1), cz = c0[2] + ((k >> 2) & 1);
    float w = ((k & 1) ? f[0] : 1.f - f[0]) * (((k >> 1) & 1) ? f[1] : 1.f - f[1]) *
              (((k >> 2) & 1) ? f[2] : 1.f - f[2]);
    int64_t r;
    if (dense) {
      r = cx + cy * (R + 1) + cz * (R + 1) * (R + 1);
    } else {
      // T is a power of two and the sum is non-negative: mod T == & (T - 1)
      r = (cx + cy * 2654435761LL + cz * 805459861LL) & (T - 1);
    }
    rows[k] = level_offset + r;
    weights[k] = w;
  }
}

}  // namespace

// Both kernels loop over levels outermost: one level's table (T rows, ~1 MB at T = 2^17, F = 2) stays in
// L2 while all points visit it, instead of every point touching every level's table (a working set of L MB).
torch::Tensor hashgrid_forward(torch::Tensor x, torch::Tensor table, torch::Tensor resolutions, int64_t T) {
  TORCH_CHECK(x.device().is_cpu() && table.device().is_cpu(), "hashgrid kernel is CPU-only");
  TORCH_CHECK(x.scalar_type() == torch::kFloat && table.scalar_type() == torch::kFloat, "float32 only");
  x = x.contiguous();
  table = table.contiguous();
  auto res = resolutions.to(torch::kLong).contiguous();
  const int64_t N = x.size(0), L = res.size(0), F = table.size(1);
  auto out = torch::empty({N, L * F}, x.options());
  const float* xp = x.data_ptr<float>();
  const float* tp = table.data_ptr<float>();
  const int64_t* rp = res.data_ptr<int64_t>();
  float* op = out.data_ptr<float>();
  const int n_threads = at::get_num_threads();
  for (int64_t l = 0; l < L; ++l) {
    const int64_t R = rp[l];
    const bool dense = (R + 1) * (R + 1) * (R + 1) <= T;
#pragma omp parallel for schedule(static) num_threads(n_threads)
    for (int64_t n = 0; n < N; ++n) {
      int64_t rows[8];
      float w[8];
      corner_rows(xp + 3 * n, R, T, dense, l * T, rows, w);
      float* o = op + n * L * F + l * F;
      for (int64_t c = 0; c < F; ++c) o[c] = 0.f;
      for (int k = 0; k < 8; ++k) {
        const float* row = tp + rows[k] * F;
        for (int64_t c = 0; c < F; ++c) o[c] += w[k] * row[c];
      }
    }
  }
  return out;
}

torch::Tensor hashgrid_backward(torch::Tensor x, torch::Tensor grad_out, torch::Tensor resolutions, int64_t T,
                                int64_t rows_total) {
  x = x.contiguous();
  grad_out = grad_out.contiguous();
  auto res = resolutions.to(torch::kLong).contiguous();
  const int64_t N = x.size(0), L = res.size(0), F = grad_out.size(1) / L;
  const float* xp = x.data_ptr<float>();
  const float* gp = grad_out.data_ptr<float>();
  const int64_t* rp = res.data_ptr<int64_t>();
  auto grad_table = torch::zeros({rows_total, F}, grad_out.options());
  float* gt = grad_table.data_ptr<float>();
  // Each thread accumulates one level into its own buffer (no atomics); the buffers are then added into the
  // level's rows of grad_table. Deterministic for a fixed thread count (static schedule, fixed summation order).
  const int n_threads = at::get_num_threads();
  auto buffers = torch::empty({n_threads > 1 ? n_threads : 0, T, F}, grad_out.options());
  float* bp = n_threads > 1 ? buffers.data_ptr<float>() : nullptr;
  for (int64_t l = 0; l < L; ++l) {
    const int64_t R = rp[l];
    const bool dense = (R + 1) * (R + 1) * (R + 1) <= T;
    float* level_grad = gt + l * T * F;
    if (n_threads > 1) std::fill(bp, bp + static_cast<int64_t>(n_threads) * T * F, 0.f);
#pragma omp parallel num_threads(n_threads)
    {
      const int tid = omp_get_thread_num();
      float* acc = n_threads > 1 ? bp + static_cast<int64_t>(tid) * T * F : level_grad;
#pragma omp for schedule(static)
      for (int64_t n = 0; n < N; ++n) {
        int64_t rows[8];
        float w[8];
        corner_rows(xp + 3 * n, R, T, dense, 0, rows, w);
        const float* g = gp + n * L * F + l * F;
        for (int k = 0; k < 8; ++k) {
          float* dst = acc + rows[k] * F;
          for (int64_t c = 0; c < F; ++c) dst[c] += w[k] * g[c];
        }
      }
    }
    if (n_threads > 1) {
      for (int t = 0; t < n_threads; ++t) {
        const float* src = bp + static_cast<int64_t>(t) * T * F;
        for (int64_t i = 0; i < T * F; ++i) level_grad[i] += src[i];
      }
    }
  }
  return grad_table;
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("forward", &hashgrid_forward, "hash-grid encode (CPU)");
  m.def("backward", &hashgrid_backward, "hash-grid encode backward w.r.t. the table (CPU)");
}
