// Tile compositing of projected Gaussians on the CPU: forward and backward.
//
// Built at run time by toolkit/splat/rasterize/cpp_ext.py (torch.utils.cpp_extension.load,
// -O3 -fopenmp -ffast-math -march=native). Projection stays in PyTorch; this file does the
// per-pixel work, which is where a pure-PyTorch rasteriser spends its time and memory.
//
// Rules (same as gsplat's classic rasteriser and toolkit/splat/rasterize/torch_ref.py):
//   sigma = 0.5 (a dx^2 + c dy^2) + b dx dy,   dx = mean_x - px,  dy = mean_y - py
//   alpha = min(0.999, opacity * exp(-sigma)), skipped when sigma < 0 or alpha < 1/255
//   a pixel stops before the Gaussian that would bring its transmittance to <= 1e-4
//   out = sum_i feat_i alpha_i T_i,  T_final = prod_i (1 - alpha_i)
//
// Loop order: within a tile the Gaussians are the outer loop and the pixels the inner one,
// in groups of 8 lanes covering, row by row, the part of the Gaussian's footprint where
// alpha can reach 1/255; the inner loop is branch-free arithmetic that gcc vectorises (exp
// through glibc's libmvec, hence -ffast-math). Skipped pixels have alpha < 1/255 by
// construction, so skipping them changes nothing. The backward writes one gradient record per (tile, Gaussian) pair and sums the
// records per Gaussian afterwards in a fixed order: no atomics and run-to-run identical
// results for any thread count.

#include <torch/extension.h>

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

constexpr int kLanes = 8;  // pixels per inner loop: one AVX2 register of floats
constexpr int kGradWidth = 6;  // mean x, mean y, conic a, b, c, opacity (+ C feature grads)

struct Tiling {
  int width, height, tile, tiles_x, tiles_y;
  int threads;  // OpenMP threads for the tile loop
};

struct TileBox {
  int x0, y0, tw, th;  // origin and size (clipped to the image)
};

inline TileBox tile_box(const Tiling& tl, int t) {
  const int tx = t % tl.tiles_x, ty = t / tl.tiles_x;
  TileBox b;
  b.x0 = tx * tl.tile;
  b.y0 = ty * tl.tile;
  b.tw = std::min(b.x0 + tl.tile, tl.width) - b.x0;
  b.th = std::min(b.y0 + tl.tile, tl.height) - b.y0;
  return b;
}

// Footprint box of Gaussian g intersected with the tile, in tile-local pixel coordinates.
// Returns false when they do not overlap.
inline bool clip_rect(const int32_t* rects, int64_t g, const TileBox& b, int& lx0, int& lx1,
                      int& ly0, int& ly1) {
  const int32_t* r = rects + 4 * g;
  lx0 = std::max<int>(r[0], b.x0) - b.x0;
  lx1 = std::min<int>(r[1], b.x0 + b.tw - 1) - b.x0;
  ly0 = std::max<int>(r[2], b.y0) - b.y0;
  ly1 = std::min<int>(r[3], b.y0 + b.th - 1) - b.y0;
  return lx0 <= lx1 && ly0 <= ly1;
}

// Lane groups [c0, c1] (starts, multiples of kLanes) of one pixel row that can reach
// alpha >= 1/255: where sigma(dx, dy) <= t = ln(255 opacity), a quadratic in dx. The box
// alone wastes most of its area on thin, tilted footprints. One pixel of margin keeps
// rounding from ever dropping a contributing pixel, so results do not change.
template <typename S>
inline bool row_span(S mx, S dy, S ca, S cb, S cc, S t, int lx0, int lx1, int& c0, int& c1) {
  const S disc = cb * cb * dy * dy - ca * (cc * dy * dy - S(2) * t);
  if (!(disc >= S(0))) return false;
  const S sq = std::sqrt(disc);
  const S lim = S(1e6);
  const S lo = std::max(-lim, std::min(lim, mx + (cb * dy - sq) / ca - S(1)));
  const S hi = std::max(-lim, std::min(lim, mx + (cb * dy + sq) / ca + S(1)));
  const int x0 = std::max(lx0, int(std::floor(lo)));
  const int x1 = std::min(lx1, int(std::ceil(hi)));
  if (x0 > x1) return false;
  c0 = (x0 / kLanes) * kLanes;
  c1 = (x1 / kLanes) * kLanes;
  return true;
}

// Per-pixel state of a tile lives on the stack in [TS * TS] arrays (row stride TS); pixels
// of a tile cut by the image border are padding that never becomes active.
template <typename S, int C, int TS>
void forward_tile(const Tiling& tl, int t, const S* means2d, const S* conics, const S* feats,
                  const S* opac, const int32_t* rects, const int32_t* offsets,
                  const int32_t* ids, S* out, S* out_T, int32_t* out_last) {
  constexpr int NP = TS * TS;
  const TileBox b = tile_box(tl, t);
  alignas(64) S T[NP];
  alignas(64) S active[NP];  // 1 while the pixel accumulates, 0 once saturated or padding
  alignas(64) S acc[C][NP];
  alignas(64) int32_t last[NP];
  for (int i = 0; i < NP; ++i) {
    T[i] = S(1);
    active[i] = ((i % TS) < b.tw && (i / TS) < b.th) ? S(1) : S(0);
    last[i] = -1;
    for (int c = 0; c < C; ++c) acc[c][i] = S(0);
  }
  const S amin = S(1) / S(255), amax = S(0.999), tmin = S(1e-4);
  int n_live = b.tw * b.th;
  for (int32_t k = offsets[t]; k < offsets[t + 1] && n_live > 0; ++k) {
    const int64_t g = ids[k];
    int lx0, lx1, ly0, ly1;
    if (!clip_rect(rects, g, b, lx0, lx1, ly0, ly1)) continue;
    const S mx = means2d[2 * g] - S(b.x0), my = means2d[2 * g + 1] - S(b.y0);
    const S ca = conics[3 * g], cb = conics[3 * g + 1], cc = conics[3 * g + 2];
    const S op = opac[g];
    const S tcut = std::log(op / amin);
    S col[C];
    for (int c = 0; c < C; ++c) col[c] = feats[C * g + c];
    for (int ly = ly0; ly <= ly1; ++ly) {
      const S dy = my - S(ly);
      int cx0, cx1;
      if (!row_span(mx, dy, ca, cb, cc, tcut, lx0, lx1, cx0, cx1)) continue;
      for (int cs = cx0; cs <= cx1; cs += kLanes) {
        const int base = ly * TS + cs;
        int done_here = 0;
#pragma omp simd reduction(+ : done_here)
        for (int j = 0; j < kLanes; ++j) {
          const int i = base + j;
          const S dx = mx - S(cs + j);
          const S sigma = S(0.5) * (ca * dx * dx + cc * dy * dy) + cb * dx * dy;
          const S alpha = std::min(amax, op * std::exp(-sigma));
          const S Ti = T[i];
          const S nT = Ti * (S(1) - alpha);
          const bool ok = (sigma >= S(0)) & (alpha >= amin) & (active[i] > S(0));
          const bool term = ok & (nT <= tmin);
          const bool use = ok & !term;
          const S w = use ? alpha * Ti : S(0);
          for (int c = 0; c < C; ++c) acc[c][i] += w * col[c];
          T[i] = use ? nT : Ti;
          active[i] = term ? S(0) : active[i];
          last[i] = use ? k : last[i];
          done_here += term ? 1 : 0;
        }
        n_live -= done_here;
      }
    }
  }
  for (int ly = 0; ly < b.th; ++ly) {
    for (int lx = 0; lx < b.tw; ++lx) {
      const int i = ly * TS + lx;
      const int64_t p = int64_t(b.y0 + ly) * tl.width + (b.x0 + lx);
      for (int c = 0; c < C; ++c) out[C * p + c] = acc[c][i];
      out_T[p] = T[i];
      out_last[p] = last[i];
    }
  }
}

template <typename S, int C, int TS>
void backward_tile(const Tiling& tl, int t, const S* means2d, const S* conics, const S* feats,
                   const S* opac, const int32_t* rects, const int32_t* offsets,
                   const int32_t* ids, const S* T_final, const int32_t* last_in,
                   const S* g_out, const S* g_T, S* pair_grads) {
  constexpr int NP = TS * TS;
  const TileBox b = tile_box(tl, t);
  alignas(64) S T[NP];
  alignas(64) S gTT[NP];  // -dL/dT_final * T_final: the alpha-output term per pixel
  alignas(64) S gout[C][NP];
  alignas(64) S behind[C][NP];  // features composited behind the current Gaussian
  alignas(64) int32_t last[NP];
  int32_t kmax = -1;
  for (int i = 0; i < NP; ++i) {
    const int lx = i % TS, ly = i / TS;
    const bool inside = lx < b.tw && ly < b.th;
    const int64_t p = int64_t(b.y0 + ly) * tl.width + (b.x0 + lx);
    T[i] = inside ? T_final[p] : S(1);
    gTT[i] = inside ? -g_T[p] * T_final[p] : S(0);
    last[i] = inside ? last_in[p] : -1;  // padding pixels never take part
    kmax = std::max(kmax, last[i]);
    for (int c = 0; c < C; ++c) {
      gout[c][i] = inside ? g_out[C * p + c] : S(0);
      behind[c][i] = S(0);
    }
  }
  const S amin = S(1) / S(255), amax = S(0.999);
  constexpr int R = kGradWidth + C;
  alignas(64) S fw[kLanes];  // per-lane weight alpha * T of this Gaussian
  for (int32_t k = kmax; k >= offsets[t]; --k) {
    const int64_t g = ids[k];
    int lx0, lx1, ly0, ly1;
    if (!clip_rect(rects, g, b, lx0, lx1, ly0, ly1)) continue;
    const S mx = means2d[2 * g] - S(b.x0), my = means2d[2 * g + 1] - S(b.y0);
    const S ca = conics[3 * g], cb = conics[3 * g + 1], cc = conics[3 * g + 2];
    const S op = opac[g];
    const S tcut = std::log(op / amin);
    S col[C];
    for (int c = 0; c < C; ++c) col[c] = feats[C * g + c];
    S v_mx = 0, v_my = 0, v_a = 0, v_b = 0, v_c = 0, v_op = 0;
    S v_col[C];
    for (int c = 0; c < C; ++c) v_col[c] = S(0);
    for (int ly = ly0; ly <= ly1; ++ly) {
      const S dy = my - S(ly);
      int cx0, cx1;
      if (!row_span(mx, dy, ca, cb, cc, tcut, lx0, lx1, cx0, cx1)) continue;
      for (int cs = cx0; cs <= cx1; cs += kLanes) {
        const int base = ly * TS + cs;
        S r_mx = 0, r_my = 0, r_a = 0, r_b = 0, r_c = 0, r_op = 0;
#pragma omp simd reduction(+ : r_mx, r_my, r_a, r_b, r_c, r_op)
        for (int j = 0; j < kLanes; ++j) {
          const int i = base + j;
          const S dx = mx - S(cs + j);
          const S sigma = S(0.5) * (ca * dx * dx + cc * dy * dy) + cb * dx * dy;
          const S vis = std::exp(-sigma);
          const S raw = op * vis;
          const S alpha = std::min(amax, raw);
          const bool valid = (k <= last[i]) & (sigma >= S(0)) & (alpha >= amin);
          const S ra = S(1) / (S(1) - alpha);
          const S Ti = valid ? T[i] * ra : T[i];  // transmittance in front of this Gaussian
          const S fac = valid ? alpha * Ti : S(0);
          S v_alpha = gTT[i] * ra;
          for (int c = 0; c < C; ++c) {
            v_alpha += (col[c] * Ti - behind[c][i] * ra) * gout[c][i];
            behind[c][i] += col[c] * fac;
          }
          fw[j] = fac;
          T[i] = Ti;
          const bool free = valid & (raw <= amax);  // clamped alpha has no gradient
          const S v_sigma = free ? -raw * v_alpha : S(0);
          r_a += S(0.5) * dx * dx * v_sigma;
          r_b += dx * dy * v_sigma;
          r_c += S(0.5) * dy * dy * v_sigma;
          r_mx += v_sigma * (ca * dx + cb * dy);
          r_my += v_sigma * (cb * dx + cc * dy);
          r_op += free ? vis * v_alpha : S(0);
        }
        // Feature gradients in a second pass: array reductions do not vectorise above.
        for (int c = 0; c < C; ++c) {
          S r = 0;
#pragma omp simd reduction(+ : r)
          for (int j = 0; j < kLanes; ++j) r += fw[j] * gout[c][base + j];
          v_col[c] += r;
        }
        v_mx += r_mx;
        v_my += r_my;
        v_a += r_a;
        v_b += r_b;
        v_c += r_c;
        v_op += r_op;
      }
    }
    S* pg = pair_grads + int64_t(R) * k;
    pg[0] = v_mx;
    pg[1] = v_my;
    pg[2] = v_a;
    pg[3] = v_b;
    pg[4] = v_c;
    pg[5] = v_op;
    for (int c = 0; c < C; ++c) pg[kGradWidth + c] = v_col[c];
  }
}

Tiling make_tiling(int64_t width, int64_t height, int64_t tile, int64_t threads) {
  TORCH_CHECK(tile == 8 || tile == 16 || tile == 32, "tile size must be 8, 16 or 32, got ", tile);
  TORCH_CHECK(width > 0 && height > 0, "image size must be positive");
  Tiling tl;
  tl.width = int(width);
  tl.height = int(height);
  tl.tile = int(tile);
  tl.tiles_x = int((width + tile - 1) / tile);
  tl.tiles_y = int((height + tile - 1) / tile);
  tl.threads = threads > 0 ? int(threads) : at::get_num_threads();
  return tl;
}

void check_inputs(const torch::Tensor& means2d, const torch::Tensor& conics,
                  const torch::Tensor& feats, const torch::Tensor& opac,
                  const torch::Tensor& rects, const torch::Tensor& offsets,
                  const torch::Tensor& ids, const Tiling& tl) {
  const auto M = means2d.size(0);
  TORCH_CHECK(means2d.dim() == 2 && means2d.size(1) == 2, "means2d must be [M, 2]");
  TORCH_CHECK(conics.dim() == 2 && conics.size(0) == M && conics.size(1) == 3,
              "conics must be [M, 3]");
  TORCH_CHECK(feats.dim() == 2 && feats.size(0) == M, "features must be [M, C]");
  TORCH_CHECK(opac.dim() == 1 && opac.size(0) == M, "opacities must be [M]");
  TORCH_CHECK(rects.dim() == 2 && rects.size(0) == M && rects.size(1) == 4 &&
                  rects.scalar_type() == torch::kInt32,
              "rects must be int32 [M, 4]");
  TORCH_CHECK(offsets.scalar_type() == torch::kInt32 &&
                  offsets.numel() == int64_t(tl.tiles_x) * tl.tiles_y + 1,
              "offsets must be int32 [tiles + 1]");
  TORCH_CHECK(ids.scalar_type() == torch::kInt32 && ids.dim() == 1, "ids must be int32 [P]");
  for (const auto* x : {&means2d, &conics, &feats, &opac, &rects, &offsets, &ids}) {
    TORCH_CHECK(x->device().is_cpu() && x->is_contiguous(), "inputs must be contiguous CPU");
  }
  TORCH_CHECK(conics.scalar_type() == means2d.scalar_type() &&
                  feats.scalar_type() == means2d.scalar_type() &&
                  opac.scalar_type() == means2d.scalar_type(),
              "float inputs must share one dtype");
}

template <typename F>
void for_each_tile(const Tiling& tl, F&& f) {
  const int n = tl.tiles_x * tl.tiles_y;
  // Tiles differ wildly in work (sky vs. textured wall), hence dynamic scheduling, which
  // also means a thread descheduled by a busy machine delays the end by one tile at most.
  // The thread count is the caller's (<= 0: torch's).
#pragma omp parallel for schedule(dynamic, 1) num_threads(tl.threads)
  for (int t = 0; t < n; ++t) f(t);
}

template <typename S, int C, int TS>
std::vector<torch::Tensor> forward_impl(const torch::Tensor& means2d, const torch::Tensor& conics,
                                        const torch::Tensor& feats, const torch::Tensor& opac,
                                        const torch::Tensor& rects, const torch::Tensor& offsets,
                                        const torch::Tensor& ids, const Tiling& tl) {
  auto fopt = means2d.options();
  auto out = torch::empty({tl.height, tl.width, C}, fopt);
  auto out_T = torch::empty({tl.height, tl.width}, fopt);
  auto out_last = torch::empty({tl.height, tl.width}, fopt.dtype(torch::kInt32));
  const S* pm = means2d.data_ptr<S>();
  const S* pc = conics.data_ptr<S>();
  const S* pf = feats.data_ptr<S>();
  const S* po = opac.data_ptr<S>();
  const int32_t* pr = rects.data_ptr<int32_t>();
  const int32_t* poff = offsets.data_ptr<int32_t>();
  const int32_t* pid = ids.data_ptr<int32_t>();
  S* o = out.data_ptr<S>();
  S* oT = out_T.data_ptr<S>();
  int32_t* oL = out_last.data_ptr<int32_t>();
  for_each_tile(tl, [&](int t) {
    forward_tile<S, C, TS>(tl, t, pm, pc, pf, po, pr, poff, pid, o, oT, oL);
  });
  return {out, out_T, out_last};
}

template <typename S, int C, int TS>
std::vector<torch::Tensor> backward_impl(
    const torch::Tensor& means2d, const torch::Tensor& conics, const torch::Tensor& feats,
    const torch::Tensor& opac, const torch::Tensor& rects, const torch::Tensor& offsets,
    const torch::Tensor& ids, const torch::Tensor& T_final, const torch::Tensor& last,
    const torch::Tensor& g_out, const torch::Tensor& g_T, const Tiling& tl) {
  const int64_t M = means2d.size(0), P = ids.size(0);
  constexpr int R = kGradWidth + C;
  auto pair = torch::zeros({P, R}, means2d.options());
  const S* pm = means2d.data_ptr<S>();
  const S* pc = conics.data_ptr<S>();
  const S* pf = feats.data_ptr<S>();
  const S* po = opac.data_ptr<S>();
  const int32_t* pr = rects.data_ptr<int32_t>();
  const int32_t* poff = offsets.data_ptr<int32_t>();
  const int32_t* pid = ids.data_ptr<int32_t>();
  const S* pT = T_final.data_ptr<S>();
  const int32_t* pL = last.data_ptr<int32_t>();
  const S* pgo = g_out.data_ptr<S>();
  const S* pgT = g_T.data_ptr<S>();
  S* pp = pair.data_ptr<S>();
  for_each_tile(tl, [&](int t) {
    backward_tile<S, C, TS>(tl, t, pm, pc, pf, po, pr, poff, pid, pT, pL, pgo, pgT, pp);
  });
  // Sum the per-pair records per Gaussian in pair order: deterministic, and cheap next to
  // the pixel loops (P * (6 + C) additions).
  auto acc = torch::zeros({M, R}, means2d.options());
  S* pa = acc.data_ptr<S>();
  for (int64_t k = 0; k < P; ++k) {
    S* dst = pa + int64_t(R) * pid[k];
    const S* src = pp + int64_t(R) * k;
    for (int r = 0; r < R; ++r) dst[r] += src[r];
  }
  auto g_means2d = acc.slice(1, 0, 2).contiguous();
  auto g_conics = acc.slice(1, 2, 5).contiguous();
  auto g_opac = acc.select(1, 5).contiguous();
  auto g_feats = acc.slice(1, kGradWidth, R).contiguous();
  return {g_means2d, g_conics, g_feats, g_opac};
}

#define DISPATCH_CHANNELS(C_RUNTIME, ...)                                        \
  [&] {                                                                          \
    switch (C_RUNTIME) {                                                         \
      case 1: { constexpr int C = 1; return __VA_ARGS__(); }                     \
      case 3: { constexpr int C = 3; return __VA_ARGS__(); }                     \
      case 4: { constexpr int C = 4; return __VA_ARGS__(); }                     \
      default: TORCH_CHECK(false, "feature channels must be 1, 3 or 4, got ", C_RUNTIME); \
    }                                                                            \
  }()

#define DISPATCH_TILE(TS_RUNTIME, ...)                                           \
  [&] {                                                                          \
    switch (TS_RUNTIME) {                                                        \
      case 8: { constexpr int TS = 8; return __VA_ARGS__(); }                    \
      case 16: { constexpr int TS = 16; return __VA_ARGS__(); }                  \
      default: { constexpr int TS = 32; return __VA_ARGS__(); }                  \
    }                                                                            \
  }()

std::vector<torch::Tensor> composite_forward(torch::Tensor means2d, torch::Tensor conics,
                                             torch::Tensor feats, torch::Tensor opac,
                                             torch::Tensor rects, torch::Tensor offsets,
                                             torch::Tensor ids, int64_t width, int64_t height,
                                             int64_t tile, int64_t threads) {
  const Tiling tl = make_tiling(width, height, tile, threads);
  check_inputs(means2d, conics, feats, opac, rects, offsets, ids, tl);
  std::vector<torch::Tensor> result;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "composite_forward", [&] {
    result = DISPATCH_CHANNELS(int(feats.size(1)), [&] {
      return DISPATCH_TILE(tl.tile, [&] {
        return forward_impl<scalar_t, C, TS>(means2d, conics, feats, opac, rects, offsets, ids,
                                             tl);
      });
    });
  });
  return result;
}

std::vector<torch::Tensor> composite_backward(torch::Tensor means2d, torch::Tensor conics,
                                              torch::Tensor feats, torch::Tensor opac,
                                              torch::Tensor rects, torch::Tensor offsets,
                                              torch::Tensor ids, int64_t width, int64_t height,
                                              int64_t tile, torch::Tensor T_final,
                                              torch::Tensor last, torch::Tensor g_out,
                                              torch::Tensor g_T, int64_t threads) {
  const Tiling tl = make_tiling(width, height, tile, threads);
  check_inputs(means2d, conics, feats, opac, rects, offsets, ids, tl);
  g_out = g_out.contiguous();
  g_T = g_T.contiguous();
  TORCH_CHECK(g_out.scalar_type() == means2d.scalar_type() &&
                  g_T.scalar_type() == means2d.scalar_type(),
              "gradients must have the inputs' dtype");
  std::vector<torch::Tensor> result;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "composite_backward", [&] {
    result = DISPATCH_CHANNELS(int(feats.size(1)), [&] {
      return DISPATCH_TILE(tl.tile, [&] {
        return backward_impl<scalar_t, C, TS>(means2d, conics, feats, opac, rects, offsets, ids,
                                              T_final.contiguous(), last.contiguous(), g_out,
                                              g_T, tl);
      });
    });
  });
  return result;
}

// Tile lists by counting sort: Gaussians visited in depth order, so each tile's list comes
// out front to back without a per-tile sort. O(M + P), single pass.
std::vector<torch::Tensor> bin_tiles(torch::Tensor rects, torch::Tensor order, int64_t width,
                                     int64_t height, int64_t tile) {
  const Tiling tl = make_tiling(width, height, tile, 1);
  TORCH_CHECK(rects.scalar_type() == torch::kInt32 && rects.is_contiguous(),
              "rects must be contiguous int32 [M, 4]");
  TORCH_CHECK(order.scalar_type() == torch::kInt64 && order.is_contiguous(),
              "order must be contiguous int64 [M]");
  const int64_t M = rects.size(0);
  const int n_tiles = tl.tiles_x * tl.tiles_y;
  const int32_t* r = rects.data_ptr<int32_t>();
  const int64_t* o = order.data_ptr<int64_t>();
  auto offsets = torch::zeros({n_tiles + 1}, rects.options());
  int32_t* off = offsets.data_ptr<int32_t>();
  auto tiles_of = [&](int64_t g, int& tx0, int& tx1, int& ty0, int& ty1) {
    const int32_t* rg = r + 4 * g;
    if (rg[0] > rg[1] || rg[2] > rg[3]) return false;
    tx0 = rg[0] / tl.tile;
    tx1 = rg[1] / tl.tile;
    ty0 = rg[2] / tl.tile;
    ty1 = rg[3] / tl.tile;
    return true;
  };
  int tx0, tx1, ty0, ty1;
  for (int64_t g = 0; g < M; ++g) {
    if (!tiles_of(g, tx0, tx1, ty0, ty1)) continue;
    for (int ty = ty0; ty <= ty1; ++ty)
      for (int tx = tx0; tx <= tx1; ++tx) off[ty * tl.tiles_x + tx + 1] += 1;
  }
  for (int t = 0; t < n_tiles; ++t) off[t + 1] += off[t];
  auto ids = torch::empty({int64_t(off[n_tiles])}, rects.options().dtype(torch::kInt32));
  int32_t* pid = ids.data_ptr<int32_t>();
  std::vector<int32_t> cursor(off, off + n_tiles);
  for (int64_t j = 0; j < M; ++j) {
    const int64_t g = o[j];
    if (!tiles_of(g, tx0, tx1, ty0, ty1)) continue;
    for (int ty = ty0; ty <= ty1; ++ty)
      for (int tx = tx0; tx <= tx1; ++tx) pid[cursor[ty * tl.tiles_x + tx]++] = int32_t(g);
  }
  return {offsets, ids};
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("composite_forward", &composite_forward,
        "accum [H, W, C], T_final [H, W], last pair index [H, W]");
  m.def("composite_backward", &composite_backward,
        "gradients for means2d, conics, features, opacities");
  m.def("bin_tiles", &bin_tiles, "tile offsets [T + 1] and depth-ordered ids [P]");
}
