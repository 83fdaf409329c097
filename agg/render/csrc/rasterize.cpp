// Tile-based Gaussian compositing on the CPU (C++ / OpenMP), forward and backward.
//
// The plain-torch twin is agg/render/raster_torch.py; tests/test_render_cpu.py compares the two on values and
// gradients. Projection and SH stay in torch autograd; this file only composites screen-space Gaussians:
//
//   accum[p] = sum_i T_i alpha_i c_i,   T_i = prod_{j<i} (1 - alpha_j),   alpha_out[p] = 1 - T_final[p]
//
// Rules shared with the reference (change both or neither):
//   * Gaussians are composited in order of increasing depth; ties keep input order (stable radix sort).
//   * A pair is skipped iff sigma < 0 or sigma > log(255 o)  (alpha would be < 1/255): no exp() for it.
//   * alpha = min(0.99, o exp(-sigma)); where clamped, the opacity and conic gradients are zero.
//   * A pixel stops at the first pair whose inclusion takes T below 1e-4; that pair is excluded.
//
// Design (2-core friendly):
//   * Binning by counting sort: Gaussians are radix-sorted by depth once, then scattered into 16x16 tiles in a
//     stable, parallel pass, so every tile list is already in depth order; no global (tile, depth) sort.
//   * One thread per tile, Gaussian-outer loop over each Gaussian's opacity-aware pixel box clipped to the tile;
//     per-pixel state lives in a thread-local tile buffer laid out channel-major for SIMD over pixels.
//   * Backward walks each tile back to front, writes one gradient row per (tile, Gaussian) intersection and
//     reduces rows per Gaussian afterwards: no atomics.
//   * Pixel convention (OpenCV): pixel (row i, column j) is sampled at (x, y) = (j, i).

#include <torch/extension.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

#ifdef _OPENMP
#include <omp.h>
#endif

namespace {

constexpr int TILE = 16;
constexpr int TILE_PIX = TILE * TILE;
constexpr float ALPHA_MAX = 0.99f;
constexpr float T_MIN = 1e-4f;
constexpr float MAX_EXTENT = 1.0e6f;

inline int num_threads() {
#ifdef _OPENMP
  return omp_get_max_threads();
#else
  return 1;
#endif
}

inline int thread_id() {
#ifdef _OPENMP
  return omp_get_thread_num();
#else
  return 0;
#endif
}

// Per-Gaussian screen data, precomputed once per call.
struct Splat {
  float mx, my;     // 2D mean, px
  float a, b, c;    // conic
  float o;          // opacity
  float thr;        // sigma threshold log(255 o)
  int x0, x1, y0, y1;  // inclusive pixel box, clipped to the image
};

// The pixel box {sigma <= thr}, widened by 0.1 % + 0.01 px so rounding never cuts the ellipse the reference sees.
inline bool make_splat(const float* m2, const float* con, float o, float thr_in, int W, int H, Splat& s) {
  s.mx = m2[0];
  s.my = m2[1];
  s.a = con[0];
  s.b = con[1];
  s.c = con[2];
  s.o = o;
  if (!(o >= 1.0f / 255.0f)) return false;
  s.thr = thr_in;  // log(255 o), computed once in torch (projection.opacity_threshold) and shared
  if (!std::isfinite(s.mx) || !std::isfinite(s.my) || !std::isfinite(s.a) || !std::isfinite(s.b) ||
      !std::isfinite(s.c))
    return false;
  const float det = s.a * s.c - s.b * s.b;
  const float thr = std::max(s.thr, 0.0f);
  float ex = MAX_EXTENT, ey = MAX_EXTENT;
  if (det > 0.0f) {
    ex = std::min(MAX_EXTENT, std::sqrt(2.0f * thr * std::fabs(s.c) / det) * 1.001f + 0.01f);
    ey = std::min(MAX_EXTENT, std::sqrt(2.0f * thr * std::fabs(s.a) / det) * 1.001f + 0.01f);
    if (!std::isfinite(ex)) ex = MAX_EXTENT;
    if (!std::isfinite(ey)) ey = MAX_EXTENT;
  }
  const float fx0 = std::ceil(s.mx - ex), fx1 = std::floor(s.mx + ex);
  const float fy0 = std::ceil(s.my - ey), fy1 = std::floor(s.my + ey);
  if (fx1 < 0.0f || fy1 < 0.0f || fx0 > float(W - 1) || fy0 > float(H - 1)) return false;
  s.x0 = int(std::max(fx0, 0.0f));
  s.x1 = int(std::min(fx1, float(W - 1)));
  s.y0 = int(std::max(fy0, 0.0f));
  s.y1 = int(std::min(fy1, float(H - 1)));
  return s.x0 <= s.x1 && s.y0 <= s.y1;
}

// sigma = d^T Q d / 2 with d = mean - pixel. The torch reference evaluates the same expression in the same order
// (the extension is built with -ffp-contract=off), so both agree bit for bit on which pairs are skipped.
inline float sigma_of(const Splat& s, float dx, float dy) {
  return 0.5f * s.a * dx * dx + 0.5f * s.c * dy * dy + s.b * dy * dx;
}

// Stable LSD radix sort of (positive float key, id) pairs: 3 passes of 11 bits over the key's bit pattern.
void radix_sort_by_depth(std::vector<uint32_t>& keys, std::vector<int32_t>& ids) {
  const size_t n = keys.size();
  std::vector<uint32_t> k2(n);
  std::vector<int32_t> i2(n);
  for (int shift = 0; shift < 32; shift += 11) {
    size_t count[2049] = {0};
    for (size_t i = 0; i < n; ++i) count[((keys[i] >> shift) & 2047u) + 1]++;
    for (int b = 0; b < 2048; ++b) count[b + 1] += count[b];
    for (size_t i = 0; i < n; ++i) {
      const size_t dst = count[(keys[i] >> shift) & 2047u]++;
      k2[dst] = keys[i];
      i2[dst] = ids[i];
    }
    keys.swap(k2);
    ids.swap(i2);
  }
}

inline uint32_t float_key(float v) {
  // Depths of visible Gaussians are > near > 0, so the IEEE bit pattern orders like the value.
  uint32_t u;
  std::memcpy(&u, &v, sizeof(u));
  return u;
}

struct Binning {
  int tiles_x = 0, tiles_y = 0;
  std::vector<Splat> splats;         // [N]
  std::vector<int32_t> sorted;       // [Nv] Gaussian ids in depth order
  std::vector<int64_t> gen_offset;   // [Nv + 1] first intersection of sorted[i], in generation order
  std::vector<int64_t> tile_start;   // [n_tiles + 1]
  std::vector<int32_t> isect_ids;    // [M] Gaussian id per intersection, grouped by tile, depth-ordered
  std::vector<int64_t> gen_to_tile;  // [M] generation index -> position in isect_ids
};

Binning bin_gaussians(const torch::Tensor& means2d, const torch::Tensor& conics, const torch::Tensor& opacities,
                      const torch::Tensor& thresholds, const torch::Tensor& depths, const torch::Tensor& visible, int W, int H, bool need_map) {
  Binning bn;
  const int64_t N = means2d.size(0);
  bn.tiles_x = (W + TILE - 1) / TILE;
  bn.tiles_y = (H + TILE - 1) / TILE;
  const int n_tiles = bn.tiles_x * bn.tiles_y;
  const float* m2 = means2d.data_ptr<float>();
  const float* con = conics.data_ptr<float>();
  const float* op = opacities.data_ptr<float>();
  const float* thp = thresholds.data_ptr<float>();
  const float* dp = depths.data_ptr<float>();
  const bool* vis = visible.data_ptr<bool>();

  bn.splats.resize(N);
  std::vector<uint8_t> ok(N, 0);
#pragma omp parallel for schedule(static)
  for (int64_t g = 0; g < N; ++g) {
    ok[g] = vis[g] && make_splat(m2 + 2 * g, con + 3 * g, op[g], thp[g], W, H, bn.splats[g]) ? 1 : 0;
  }
  std::vector<uint32_t> keys;
  keys.reserve(N);
  bn.sorted.reserve(N);
  for (int64_t g = 0; g < N; ++g) {
    if (ok[g]) {
      keys.push_back(float_key(dp[g]));
      bn.sorted.push_back(int32_t(g));
    }
  }
  radix_sort_by_depth(keys, bn.sorted);
  const int64_t Nv = int64_t(bn.sorted.size());

  // Intersections per Gaussian, in depth order.
  bn.gen_offset.assign(Nv + 1, 0);
  for (int64_t i = 0; i < Nv; ++i) {
    const Splat& s = bn.splats[bn.sorted[i]];
    const int64_t w = s.x1 / TILE - s.x0 / TILE + 1;
    const int64_t h = s.y1 / TILE - s.y0 / TILE + 1;
    bn.gen_offset[i + 1] = bn.gen_offset[i] + w * h;
  }
  const int64_t M = bn.gen_offset[Nv];

  // Stable counting sort into tiles: each thread owns a contiguous chunk of the depth order.
  const int T = std::max(1, num_threads());
  std::vector<int64_t> counts(int64_t(T) * n_tiles, 0);
  auto chunk_of = [&](int t, int64_t& lo, int64_t& hi) {
    lo = Nv * t / T;
    hi = Nv * (t + 1) / T;
  };
#pragma omp parallel num_threads(T)
  {
    const int t = thread_id();
    int64_t lo, hi;
    chunk_of(t, lo, hi);
    int64_t* cnt = counts.data() + int64_t(t) * n_tiles;
    for (int64_t i = lo; i < hi; ++i) {
      const Splat& s = bn.splats[bn.sorted[i]];
      for (int ty = s.y0 / TILE; ty <= s.y1 / TILE; ++ty)
        for (int tx = s.x0 / TILE; tx <= s.x1 / TILE; ++tx) cnt[ty * bn.tiles_x + tx]++;
    }
  }
  bn.tile_start.assign(n_tiles + 1, 0);
  std::vector<int64_t> cursor(int64_t(T) * n_tiles);
  int64_t run = 0;
  for (int tile = 0; tile < n_tiles; ++tile) {
    bn.tile_start[tile] = run;
    for (int t = 0; t < T; ++t) {
      cursor[int64_t(t) * n_tiles + tile] = run;
      run += counts[int64_t(t) * n_tiles + tile];
    }
  }
  bn.tile_start[n_tiles] = run;
  bn.isect_ids.resize(M);
  if (need_map) bn.gen_to_tile.resize(M);
#pragma omp parallel num_threads(T)
  {
    const int t = thread_id();
    int64_t lo, hi;
    chunk_of(t, lo, hi);
    int64_t* cur = cursor.data() + int64_t(t) * n_tiles;
    for (int64_t i = lo; i < hi; ++i) {
      const int32_t g = bn.sorted[i];
      const Splat& s = bn.splats[g];
      int64_t e = bn.gen_offset[i];
      for (int ty = s.y0 / TILE; ty <= s.y1 / TILE; ++ty)
        for (int tx = s.x0 / TILE; tx <= s.x1 / TILE; ++tx) {
          const int64_t k = cur[ty * bn.tiles_x + tx]++;
          bn.isect_ids[k] = g;
          if (need_map) bn.gen_to_tile[e] = k;
          ++e;
        }
    }
  }
  return bn;
}

// Vectorisable inner step for one row segment of a Gaussian's box inside a tile (forward).
// Per-pixel tile state is channel-major: acc[c * TILE_PIX + p].
inline int composite_row(const Splat& s, const float* col, int C, int k1, float dy, float px0, int p0, int n,
                         float* Tt, uint8_t* active, int32_t* last, float* acc) {
  int finished = 0;
  for (int j = 0; j < n; ++j) {
    const int p = p0 + j;
    const float dx = s.mx - (px0 + float(j));
    const float sigma = sigma_of(s, dx, dy);
    if (!(sigma >= 0.0f && sigma <= s.thr) || !active[p]) continue;
    const float alpha = std::min(ALPHA_MAX, s.o * std::exp(-sigma));
    const float Tp = Tt[p];
    const float nT = Tp * (1.0f - alpha);
    if (nT < T_MIN) {
      active[p] = 0;
      ++finished;
      continue;
    }
    const float w = alpha * Tp;
    for (int c = 0; c < C; ++c) acc[c * TILE_PIX + p] += w * col[c];
    Tt[p] = nT;
    last[p] = k1;
  }
  return finished;
}

}  // namespace

// Forward. Returns {accum [H, W, C], T_final [H, W], last [H, W] int32: the exclusive end of each pixel's
// contributors in its tile's intersection list, which the backward pass rebuilds identically}.
std::vector<torch::Tensor> forward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor colors,
                                   torch::Tensor opacities, torch::Tensor thresholds, torch::Tensor depths,
                                   torch::Tensor visible, int64_t W, int64_t H) {
  TORCH_CHECK(means2d.dtype() == torch::kFloat32 && colors.dtype() == torch::kFloat32, "float32 inputs expected");
  const int64_t C = colors.size(1);
  Binning bn = bin_gaussians(means2d, conics, opacities, thresholds, depths, visible, int(W), int(H), false);
  const int n_tiles = bn.tiles_x * bn.tiles_y;
  auto accum = torch::zeros({H, W, C}, colors.options());
  auto T_final = torch::ones({H, W}, colors.options());
  auto last = torch::zeros({H, W}, colors.options().dtype(torch::kInt32));
  float* acc_out = accum.data_ptr<float>();
  float* T_out = T_final.data_ptr<float>();
  int32_t* last_out = last.data_ptr<int32_t>();
  const float* col = colors.data_ptr<float>();

#pragma omp parallel
  {
    std::vector<float> acc(C * TILE_PIX), Tt(TILE_PIX);
    std::vector<uint8_t> active(TILE_PIX);
    std::vector<int32_t> lst(TILE_PIX);
#pragma omp for schedule(dynamic, 1)
    for (int tile = 0; tile < n_tiles; ++tile) {
      const int tx0 = (tile % bn.tiles_x) * TILE, ty0 = (tile / bn.tiles_x) * TILE;
      const int tw = std::min<int>(TILE, int(W) - tx0), th = std::min<int>(TILE, int(H) - ty0);
      std::fill(acc.begin(), acc.end(), 0.0f);
      std::fill(Tt.begin(), Tt.end(), 1.0f);
      std::fill(active.begin(), active.end(), 1);
      const int64_t start = bn.tile_start[tile], end = bn.tile_start[tile + 1];
      std::fill(lst.begin(), lst.end(), int32_t(start));
      int alive = tw * th;
      for (int64_t k = start; k < end && alive > 0; ++k) {
        const int32_t g = bn.isect_ids[k];
        const Splat& s = bn.splats[g];
        const int x0 = std::max(s.x0, tx0), x1 = std::min(s.x1, tx0 + tw - 1);
        const int y0 = std::max(s.y0, ty0), y1 = std::min(s.y1, ty0 + th - 1);
        for (int y = y0; y <= y1; ++y) {
          alive -= composite_row(s, col + int64_t(g) * C, int(C), int32_t(k + 1), s.my - float(y), float(x0),
                                 (y - ty0) * TILE + (x0 - tx0), x1 - x0 + 1, Tt.data(), active.data(), lst.data(),
                                 acc.data());
        }
      }
      for (int yy = 0; yy < th; ++yy)
        for (int xx = 0; xx < tw; ++xx) {
          const int p = yy * TILE + xx;
          const int64_t o = (int64_t(ty0 + yy) * W + tx0 + xx);
          for (int c = 0; c < C; ++c) acc_out[o * C + c] = acc[c * TILE_PIX + p];
          T_out[o] = Tt[p];
          last_out[o] = lst[p];
        }
    }
  }
  return {accum, T_final, last};
}

// Backward. Given dL/daccum [H, W, C] and dL/dalpha_out [H, W], returns
// {dL/dmeans2d [N, 2], dL/dconics [N, 3], dL/dcolors [N, C], dL/dopacities [N]}.
std::vector<torch::Tensor> backward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor colors,
                                    torch::Tensor opacities, torch::Tensor thresholds, torch::Tensor depths,
                                    torch::Tensor visible, int64_t W, int64_t H, torch::Tensor T_final, torch::Tensor last, torch::Tensor grad_accum,
                                    torch::Tensor grad_alpha) {
  const int64_t N = means2d.size(0);
  const int64_t C = colors.size(1);
  Binning bn = bin_gaussians(means2d, conics, opacities, thresholds, depths, visible, int(W), int(H), true);
  const int n_tiles = bn.tiles_x * bn.tiles_y;
  const int64_t M = int64_t(bn.isect_ids.size());
  const int64_t G = 6 + C;  // row: mx, my, a, b, c, o, colour[C]
  std::vector<float> rows(M * G);
  const float* col = colors.data_ptr<float>();
  const float* Tf = T_final.data_ptr<float>();
  const int32_t* lastp = last.data_ptr<int32_t>();
  const float* gacc = grad_accum.data_ptr<float>();
  const float* galpha = grad_alpha.data_ptr<float>();

#pragma omp parallel
  {
    std::vector<float> R(C * TILE_PIX), gC(C * TILE_PIX), Tt(TILE_PIX), Tfin(TILE_PIX), gA(TILE_PIX);
    std::vector<int32_t> lst(TILE_PIX);
    std::vector<double> gcol(C);
#pragma omp for schedule(dynamic, 1)
    for (int tile = 0; tile < n_tiles; ++tile) {
      const int tx0 = (tile % bn.tiles_x) * TILE, ty0 = (tile / bn.tiles_x) * TILE;
      const int tw = std::min<int>(TILE, int(W) - tx0), th = std::min<int>(TILE, int(H) - ty0);
      const int64_t start = bn.tile_start[tile];
      int64_t max_last = start;
      std::fill(lst.begin(), lst.end(), int32_t(start));
      std::fill(R.begin(), R.end(), 0.0f);
      for (int yy = 0; yy < th; ++yy)
        for (int xx = 0; xx < tw; ++xx) {
          const int p = yy * TILE + xx;
          const int64_t o = int64_t(ty0 + yy) * W + tx0 + xx;
          lst[p] = lastp[o];
          max_last = std::max<int64_t>(max_last, lastp[o]);
          Tt[p] = Tfin[p] = Tf[o];
          gA[p] = galpha[o];
          for (int c = 0; c < C; ++c) gC[c * TILE_PIX + p] = gacc[o * C + c];
        }
      for (int64_t k = max_last - 1; k >= start; --k) {
        const int32_t g = bn.isect_ids[k];
        const Splat& s = bn.splats[g];
        const float* cg = col + int64_t(g) * C;
        const int x0 = std::max(s.x0, tx0), x1 = std::min(s.x1, tx0 + tw - 1);
        const int y0 = std::max(s.y0, ty0), y1 = std::min(s.y1, ty0 + th - 1);
        double g_mx = 0, g_my = 0, g_a = 0, g_b = 0, g_c = 0, g_o = 0;
        std::fill(gcol.begin(), gcol.end(), 0.0);
        for (int y = y0; y <= y1; ++y) {
          const float dy = s.my - float(y);
          for (int x = x0; x <= x1; ++x) {
            const int p = (y - ty0) * TILE + (x - tx0);
            if (k >= lst[p]) continue;
            const float dx = s.mx - float(x);
            const float sigma = sigma_of(s, dx, dy);
            if (!(sigma >= 0.0f && sigma <= s.thr)) continue;
            const float G_ = std::exp(-sigma);
            const float a_raw = s.o * G_;
            const float alpha = std::min(ALPHA_MAX, a_raw);
            const float one_m = 1.0f - alpha;
            const float Ti = Tt[p] / one_m;  // transmittance in front of this Gaussian
            const float w = alpha * Ti;
            float dL_dalpha = 0.0f;
            for (int c = 0; c < C; ++c) {
              const float gc = gC[c * TILE_PIX + p];
              float& r = R[c * TILE_PIX + p];
              gcol[c] += double(w * gc);
              dL_dalpha += (cg[c] - r) * gc;
              r = alpha * cg[c] + one_m * r;
            }
            dL_dalpha = dL_dalpha * Ti + gA[p] * Tfin[p] / one_m;
            Tt[p] = Ti;
            if (a_raw <= ALPHA_MAX) {
              g_o += double(G_ * dL_dalpha);
              const float dL_dsigma = -alpha * dL_dalpha;
              g_mx += double(dL_dsigma * (s.a * dx + s.b * dy));
              g_my += double(dL_dsigma * (s.c * dy + s.b * dx));
              g_a += double(0.5f * dL_dsigma * dx * dx);
              g_b += double(dL_dsigma * dx * dy);
              g_c += double(0.5f * dL_dsigma * dy * dy);
            }
          }
        }
        float* row = rows.data() + k * G;
        row[0] = float(g_mx);
        row[1] = float(g_my);
        row[2] = float(g_a);
        row[3] = float(g_b);
        row[4] = float(g_c);
        row[5] = float(g_o);
        for (int c = 0; c < C; ++c) row[6 + c] = float(gcol[c]);
      }
      // Rows of intersections past every pixel's last contributor were never written: zero them.
      for (int64_t k = std::max(max_last, start); k < bn.tile_start[tile + 1]; ++k)
        std::fill(rows.begin() + k * G, rows.begin() + (k + 1) * G, 0.0f);
    }
  }

  auto g_means2d = torch::zeros({N, 2}, colors.options());
  auto g_conics = torch::zeros({N, 3}, colors.options());
  auto g_colors = torch::zeros({N, C}, colors.options());
  auto g_opac = torch::zeros({N}, colors.options());
  float* pm = g_means2d.data_ptr<float>();
  float* pc = g_conics.data_ptr<float>();
  float* pcol = g_colors.data_ptr<float>();
  float* po = g_opac.data_ptr<float>();
  const int64_t Nv = int64_t(bn.sorted.size());
#pragma omp parallel
  {
    std::vector<double> sum(G);
#pragma omp for schedule(static)
    for (int64_t i = 0; i < Nv; ++i) {
      std::fill(sum.begin(), sum.end(), 0.0);
      for (int64_t e = bn.gen_offset[i]; e < bn.gen_offset[i + 1]; ++e) {
        const float* row = rows.data() + bn.gen_to_tile[e] * G;
        for (int64_t j = 0; j < G; ++j) sum[j] += row[j];
      }
      const int64_t g = bn.sorted[i];
      pm[2 * g] = float(sum[0]);
      pm[2 * g + 1] = float(sum[1]);
      pc[3 * g] = float(sum[2]);
      pc[3 * g + 1] = float(sum[3]);
      pc[3 * g + 2] = float(sum[4]);
      po[g] = float(sum[5]);
      for (int64_t c = 0; c < C; ++c) pcol[g * C + c] = float(sum[6 + c]);
    }
  }
  return {g_means2d, g_conics, g_colors, g_opac};
}
