// Projection (EWA splatting) and tile compositing of Gaussians on the CPU: forward and
// backward.
//
// Built at run time by toolkit/splat/rasterize/cpp_ext.py (torch.utils.cpp_extension.load,
// -O3 -fopenmp -ffast-math -march=native). SH colours stay in PyTorch; this file does the
// per-Gaussian projection (at the end of the file) and the per-pixel work, which is where
// a pure-PyTorch rasteriser spends its time and memory.
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
#include <cstring>
#include <type_traits>
#include <vector>

namespace {

constexpr int kLanes = 8;  // pixels per inner loop: one AVX2 register of floats
constexpr double kMaxExtend = 3.33;  // footprint cap in standard deviations (gsplat's)
// Largest stored footprint half-extent (common.MAX_RADIUS_PX): the int32 cast of a radius
// past 2^31 is undefined (it gave -2^31, and the Gaussian covered no pixel).
constexpr double kMaxRadius = 1073741824.0;  // 2^30
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
        // A lane group whose pixels have all stopped (or are padding) takes nothing from
        // this Gaussian: skipping it leaves every output as it was, and on opaque walls most
        // of a tile's later Gaussians meet only such groups.
        S live = S(0);
#pragma omp simd reduction(max : live)
        for (int j = 0; j < kLanes; ++j) live = std::max(live, active[base + j]);
        if (live == S(0)) continue;
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
        // No skip of groups whose pixels all stopped before k (as the forward has): exact,
        // but the test cost more than it saved here (compositing backward +3-7 %, min of 10
        // over 13 quickstart poses, 2026-11-28), the group's lanes mostly reaching k.
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

// Sort keys of floats: unsigned integers that order as the values do, with -0 and +0
// equal and every NaN last, so that a stable sort on them gives torch.argsort(stable=True)'s
// order exactly.
template <typename S, typename U>
inline U sort_key(S v) {
  U bits;
  std::memcpy(&bits, &v, sizeof(U));
  constexpr U sign = U(1) << (8 * sizeof(U) - 1);
  if ((bits & ~sign) == 0) bits = 0;  // -0 -> +0
  // NaN: exponent all ones and a non-zero mantissa (bit tests: -ffast-math may drop isnan)
  constexpr U exp_mask = sizeof(U) == 4 ? U(0x7F800000u) : U(0x7FF0000000000000ull);
  const bool nan = (bits & exp_mask) == exp_mask && (bits & ~sign & ~exp_mask) != 0;
  if (nan) return ~U(0);
  return (bits & sign) ? ~bits : (bits | sign);
}

template <typename S, typename U>
void radix_order(const S* v, int64_t n, int64_t* out) {
  // LSD radix sort, 8 bits a pass: stable, O(n). 40,000 float depths on one core of the
  // 2-core EPYC: 0.33 ms, torch's stable argsort 3.3 ms (min of 30, 2026-11-28).
  std::vector<U> key(n), key2(n);
  std::vector<int64_t> idx2(n);
  for (int64_t i = 0; i < n; ++i) {
    key[i] = sort_key<S, U>(v[i]);
    out[i] = i;
  }
  int64_t* src_i = out;
  int64_t* dst_i = idx2.data();
  U* src_k = key.data();
  U* dst_k = key2.data();
  for (int shift = 0; shift < int(8 * sizeof(U)); shift += 8) {
    int64_t count[257] = {0};
    for (int64_t i = 0; i < n; ++i) ++count[((src_k[i] >> shift) & 0xFF) + 1];
    if (count[((src_k[0] >> shift) & 0xFF) + 1] == n) continue;  // one bucket: nothing moves
    for (int b = 0; b < 256; ++b) count[b + 1] += count[b];
    for (int64_t i = 0; i < n; ++i) {
      const int64_t d = count[(src_k[i] >> shift) & 0xFF]++;
      dst_k[d] = src_k[i];
      dst_i[d] = src_i[i];
    }
    std::swap(src_k, dst_k);
    std::swap(src_i, dst_i);
  }
  if (src_i != out) std::memcpy(out, src_i, sizeof(int64_t) * n);
}

// [M] int64: the stable ascending order of a 1-D float tensor, torch.argsort(x, stable=True).
torch::Tensor depth_order(torch::Tensor x) {
  TORCH_CHECK(x.dim() == 1 && x.device().is_cpu(), "depth_order takes a 1-D CPU tensor");
  x = x.contiguous();
  const int64_t n = x.size(0);
  auto order = torch::empty({n}, x.options().dtype(torch::kInt64));
  if (n == 0) return order;
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "depth_order", [&] {
    using U = std::conditional_t<sizeof(scalar_t) == 4, uint32_t, uint64_t>;
    radix_order<scalar_t, U>(x.data_ptr<scalar_t>(), n, order.data_ptr<int64_t>());
  });
  return order;
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


// ---------------------------------------------------------------------------------------
// EWA projection, forward and backward: the maths of common.py:project fused per Gaussian
// (PyTorch runs it as ~60 elementwise passes over [M] tensors, and as many again in its
// backward, which cost more than the compositing at training sizes).
//
// -ffast-math lets gcc assume no inf/NaN, so the visibility tests that must reject them
// (huge scales overflow exp, as in the PyTorch version) look at the float's exponent bits.

inline bool finite_bits(float v) {
  uint32_t u;
  std::memcpy(&u, &v, sizeof u);
  return (u & 0x7f800000u) != 0x7f800000u;
}

inline bool finite_bits(double v) {
  uint64_t u;
  std::memcpy(&u, &v, sizeof u);
  return (u & 0x7ff0000000000000ull) != 0x7ff0000000000000ull;
}

template <typename S>
struct ProjCam {
  S R[9], t[3];  // world-to-camera rotation (row-major) and translation
  S fx, fy, cx, cy, cxg, cyg;  // cxg, cyg: gsplat's principal point (pixel centres at +0.5)
  S lim_xp, lim_xn, lim_yp, lim_yn;  // Jacobian clamp (tangent limits of the frustum + 30%)
  S jx_c, jy_c;  // step 1's bound on the Jacobian's growth towards the clamp
  S near, far, eps2d;
  S width, height;
};

template <typename S>
ProjCam<S> make_proj_cam(const torch::Tensor& viewmat, double fx, double fy, double cx,
                         double cy, int64_t width, int64_t height, double near, double far,
                         double eps2d) {
  TORCH_CHECK(viewmat.dim() == 2 && viewmat.size(0) == 4 && viewmat.size(1) == 4 &&
                  viewmat.is_contiguous(),
              "viewmat must be contiguous [4, 4]");
  const S* v = viewmat.data_ptr<S>();
  ProjCam<S> c;
  for (int r = 0; r < 3; ++r) {
    for (int k = 0; k < 3; ++k) c.R[3 * r + k] = v[4 * r + k];
    c.t[r] = v[4 * r + 3];
  }
  // Constants in double, as the Python version computes them, then rounded once.
  const double tan_x = 0.5 * double(width) / fx, tan_y = 0.5 * double(height) / fy;
  const double cxg = cx + 0.5, cyg = cy + 0.5;
  const double lxp = (double(width) - cxg) / fx + 0.3 * tan_x, lxn = cxg / fx + 0.3 * tan_x;
  const double lyp = (double(height) - cyg) / fy + 0.3 * tan_y, lyn = cyg / fy + 0.3 * tan_y;
  c.fx = S(fx);
  c.fy = S(fy);
  c.cx = S(cx);
  c.cy = S(cy);
  c.cxg = S(cxg);
  c.cyg = S(cyg);
  c.lim_xp = S(lxp);
  c.lim_xn = S(lxn);
  c.lim_yp = S(lyp);
  c.lim_yn = S(lyn);
  c.jx_c = S(std::sqrt(1.0 + std::max(lxp, lxn) * std::max(lxp, lxn)));
  c.jy_c = S(std::sqrt(1.0 + std::max(lyp, lyn) * std::max(lyp, lyn)));
  c.near = S(near);
  c.far = S(far);
  c.eps2d = S(eps2d);
  c.width = S(width);
  c.height = S(height);
  return c;
}

// Everything the backward needs of one Gaussian's forward (recomputed there, not stored:
// cheaper than writing and reading ~60 values per Gaussian).
template <typename S>
struct Ewa {
  S x, y, z, rz, rz2, ux, uy, tx, ty;
  bool inx, iny;  // the Jacobian clamp is inactive (the gradient passes through it)
  S A0[3], A1[3];  // rows of J W_R
  S q[4], qn;  // normalised quaternion (wxyz) and the (clamped) norm it was divided by
  bool qclamp;
  S Rq[9], s[3], M0[3], M1[3], T0[3], T1[3];  // T = (J W_R R_q) S, rows 0 and 1
  S a, b, c;  // 2D covariance [[a, b], [b, c]] with the eps2d dilation
};

template <typename S>
inline void cam_point(const ProjCam<S>& cm, const S* m, S& x, S& y, S& z) {
  x = cm.R[0] * m[0] + cm.R[1] * m[1] + cm.R[2] * m[2] + cm.t[0];
  y = cm.R[3] * m[0] + cm.R[4] * m[1] + cm.R[5] * m[2] + cm.t[1];
  z = cm.R[6] * m[0] + cm.R[7] * m[1] + cm.R[8] * m[2] + cm.t[2];
}

template <typename S>
inline void ewa(const ProjCam<S>& cm, const S* m, const S* q4, const S* ls, Ewa<S>& f) {
  const S* R = cm.R;
  cam_point(cm, m, f.x, f.y, f.z);
  f.rz = S(1) / f.z;
  const S u = f.x * f.rz, v = f.y * f.rz;
  f.inx = u >= -cm.lim_xn && u <= cm.lim_xp;
  f.iny = v >= -cm.lim_yn && v <= cm.lim_yp;
  f.ux = std::min(std::max(u, -cm.lim_xn), cm.lim_xp);
  f.uy = std::min(std::max(v, -cm.lim_yn), cm.lim_yp);
  f.tx = f.z * f.ux;
  f.ty = f.z * f.uy;
  f.rz2 = f.rz * f.rz;
  for (int k = 0; k < 3; ++k) {
    f.A0[k] = cm.fx * f.rz * R[k] - cm.fx * f.tx * f.rz2 * R[6 + k];
    f.A1[k] = cm.fy * f.rz * R[3 + k] - cm.fy * f.ty * f.rz2 * R[6 + k];
  }
  const S n = std::sqrt(q4[0] * q4[0] + q4[1] * q4[1] + q4[2] * q4[2] + q4[3] * q4[3]);
  f.qclamp = n < S(1e-12);
  f.qn = f.qclamp ? S(1e-12) : n;
  for (int k = 0; k < 4; ++k) f.q[k] = q4[k] / f.qn;
  const S w = f.q[0], x = f.q[1], y = f.q[2], z = f.q[3];
  S* Q = f.Rq;
  Q[0] = 1 - 2 * (y * y + z * z);
  Q[1] = 2 * (x * y - w * z);
  Q[2] = 2 * (x * z + w * y);
  Q[3] = 2 * (x * y + w * z);
  Q[4] = 1 - 2 * (x * x + z * z);
  Q[5] = 2 * (y * z - w * x);
  Q[6] = 2 * (x * z - w * y);
  Q[7] = 2 * (y * z + w * x);
  Q[8] = 1 - 2 * (x * x + y * y);
  for (int j = 0; j < 3; ++j) {
    f.s[j] = std::exp(ls[j]);
    f.M0[j] = f.A0[0] * Q[j] + f.A0[1] * Q[3 + j] + f.A0[2] * Q[6 + j];
    f.M1[j] = f.A1[0] * Q[j] + f.A1[1] * Q[3 + j] + f.A1[2] * Q[6 + j];
    f.T0[j] = f.M0[j] * f.s[j];
    f.T1[j] = f.M1[j] * f.s[j];
  }
  f.a = f.T0[0] * f.T0[0] + f.T0[1] * f.T0[1] + f.T0[2] * f.T0[2] + cm.eps2d;
  f.b = f.T0[0] * f.T1[0] + f.T0[1] * f.T1[1] + f.T0[2] * f.T1[2];
  f.c = f.T1[0] * f.T1[0] + f.T1[1] * f.T1[1] + f.T1[2] * f.T1[2] + cm.eps2d;
}

// Step 1 of common.py:project: a cheap conservative cull (depth range, footprint bound from
// the largest scale) before the EWA maths.
template <typename S>
inline bool maybe_visible(const ProjCam<S>& cm, const S* m, const S* ls) {
  S x, y, z;
  cam_point(cm, m, x, y, z);
  if (!(finite_bits(x) && finite_bits(y) && finite_bits(z))) return false;
  if (!(z > cm.near && z < cm.far)) return false;
  const S smax = std::exp(std::max(ls[0], std::max(ls[1], ls[2])));
  const S jx = cm.fx / z * cm.jx_c, jy = cm.fy / z * cm.jy_c;
  const S rxb = S(kMaxExtend) * std::sqrt((jx * smax) * (jx * smax) + cm.eps2d) + S(1);
  const S ryb = S(kMaxExtend) * std::sqrt((jy * smax) * (jy * smax) + cm.eps2d) + S(1);
  const S u = cm.fx * x / z + cm.cxg, v = cm.fy * y / z + cm.cyg;
  return u + rxb > 0 && u - rxb < cm.width && v + ryb > 0 && v - ryb < cm.height;
}

template <typename S>
struct ProjOut {
  S mx, my, con[3], z, op;
  int32_t rx, ry;
};

// Steps 2 and 3: EWA projection, then gsplat's exact visibility rules and footprint box.
template <typename S>
inline bool project_one(const ProjCam<S>& cm, const S* m, const S* q4, const S* ls, S logit,
                        ProjOut<S>& o) {
  if (!maybe_visible(cm, m, ls)) return false;
  Ewa<S> f;
  ewa(cm, m, q4, ls, f);
  const S amin = S(1.0 / 255.0);
  const S op = S(1) / (S(1) + std::exp(-logit));
  const S mx = cm.fx * f.x * f.rz + cm.cx, my = cm.fy * f.y * f.rz + cm.cy;
  if (!(finite_bits(f.a) && finite_bits(f.b) && finite_bits(f.c) && finite_bits(mx) &&
        finite_bits(my) && finite_bits(op)))
    return false;
  const S det = f.a * f.c - f.b * f.b;
  if (!(det > 0) || !(op >= amin)) return false;
  const S extend = std::min(std::sqrt(S(2) * std::log(std::max(op, amin) / amin)), S(kMaxExtend));
  const S rx = std::ceil(extend * std::sqrt(std::max(f.a, S(0))));
  const S ry = std::ceil(extend * std::sqrt(std::max(f.c, S(0))));
  if (!(rx > 0 || ry > 0)) return false;
  const S mxd = mx + S(0.5), myd = my + S(0.5);
  if (!(mxd + rx > 0 && mxd - rx < cm.width && myd + ry > 0 && myd - ry < cm.height))
    return false;
  o.mx = mx;
  o.my = my;
  o.con[0] = f.c / det;
  o.con[1] = -f.b / det;
  o.con[2] = f.a / det;
  o.z = f.z;
  o.op = op;
  o.rx = int32_t(std::min(rx, S(kMaxRadius)));
  o.ry = int32_t(std::min(ry, S(kMaxRadius)));
  return true;
}

void check_gaussians(const torch::Tensor& means, const torch::Tensor& quats,
                     const torch::Tensor& log_scales, const torch::Tensor& logits,
                     const torch::Tensor& viewmat) {
  const auto N = means.size(0);
  TORCH_CHECK(means.dim() == 2 && means.size(1) == 3, "means must be [N, 3]");
  TORCH_CHECK(quats.dim() == 2 && quats.size(0) == N && quats.size(1) == 4,
              "quats must be [N, 4]");
  TORCH_CHECK(log_scales.dim() == 2 && log_scales.size(0) == N && log_scales.size(1) == 3,
              "log_scales must be [N, 3]");
  TORCH_CHECK(logits.dim() == 1 && logits.size(0) == N, "opacity logits must be [N]");
  for (const auto* x : {&means, &quats, &log_scales, &logits, &viewmat}) {
    TORCH_CHECK(x->device().is_cpu() && x->is_contiguous(), "inputs must be contiguous CPU");
    TORCH_CHECK(x->scalar_type() == means.scalar_type(), "float inputs must share one dtype");
  }
}

template <typename S>
std::vector<torch::Tensor> project_forward_impl(const torch::Tensor& means,
                                                const torch::Tensor& quats,
                                                const torch::Tensor& log_scales,
                                                const torch::Tensor& logits,
                                                const ProjCam<S>& cm, int nt) {
  const int64_t N = means.size(0);
  {
    const S* pm = means.data_ptr<S>();
    const S* pq = quats.data_ptr<S>();
    const S* pl = log_scales.data_ptr<S>();
    const S* po = logits.data_ptr<S>();
    // Unpacked results, then a compaction in model order (what torch.nonzero gives).
    std::vector<ProjOut<S>> all(N);
    std::vector<uint8_t> keep(N);
#pragma omp parallel for schedule(static) num_threads(nt)
    for (int64_t i = 0; i < N; ++i)
      keep[i] = project_one(cm, pm + 3 * i, pq + 4 * i, pl + 3 * i, po[i], all[i]);
    std::vector<int64_t> dst(N);
    int64_t M = 0;
    for (int64_t i = 0; i < N; ++i) {
      dst[i] = M;
      M += keep[i];
    }
    auto fopt = means.options();
    auto gids = torch::empty({M}, fopt.dtype(torch::kInt64));
    auto means2d = torch::empty({M, 2}, fopt);
    auto conics = torch::empty({M, 3}, fopt);
    auto depths = torch::empty({M}, fopt);
    auto opac = torch::empty({M}, fopt);
    auto radii = torch::empty({M, 2}, fopt.dtype(torch::kInt32));
    int64_t* pg = gids.data_ptr<int64_t>();
    S* p2 = means2d.data_ptr<S>();
    S* pc = conics.data_ptr<S>();
    S* pz = depths.data_ptr<S>();
    S* pop = opac.data_ptr<S>();
    int32_t* pr = radii.data_ptr<int32_t>();
#pragma omp parallel for schedule(static) num_threads(nt)
    for (int64_t i = 0; i < N; ++i) {
      if (!keep[i]) continue;
      const int64_t k = dst[i];
      const ProjOut<S>& o = all[i];
      pg[k] = i;
      p2[2 * k] = o.mx;
      p2[2 * k + 1] = o.my;
      for (int j = 0; j < 3; ++j) pc[3 * k + j] = o.con[j];
      pz[k] = o.z;
      pop[k] = o.op;
      pr[2 * k] = o.rx;
      pr[2 * k + 1] = o.ry;
    }
    return {gids, means2d, conics, depths, opac, radii};
  }
}

std::vector<torch::Tensor> project_forward(torch::Tensor means, torch::Tensor quats,
                                           torch::Tensor log_scales, torch::Tensor logits,
                                           torch::Tensor viewmat, double fx, double fy,
                                           double cx, double cy, int64_t width, int64_t height,
                                           double near, double far, double eps2d,
                                           int64_t threads) {
  check_gaussians(means, quats, log_scales, logits, viewmat);
  const int nt = threads > 0 ? int(threads) : at::get_num_threads();
  std::vector<torch::Tensor> result;
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_forward", [&] {
    const auto cm = make_proj_cam<scalar_t>(viewmat, fx, fy, cx, cy, width, height, near,
                                            far, eps2d);
    result = project_forward_impl<scalar_t>(means, quats, log_scales, logits, cm, nt);
  });
  return result;
}

// The viewmat gradient is a sum over Gaussians: partial sums over fixed blocks of survivors
// (independent of the thread count), added in block order, so it is identical run to run.
constexpr int64_t kViewBlock = 512;

template <typename S>
void project_backward_impl(const torch::Tensor& means, const torch::Tensor& quats,
                           const torch::Tensor& log_scales, const torch::Tensor& logits,
                           const torch::Tensor& gids, const ProjCam<S>& cm,
                           const torch::Tensor& g_means2d, const torch::Tensor& g_conics,
                           const torch::Tensor& g_depths, const torch::Tensor& g_opac,
                           bool need_viewmat, int nt, torch::Tensor& g_means,
                           torch::Tensor& g_quats, torch::Tensor& g_ls,
                           torch::Tensor& g_logits, torch::Tensor& g_view) {
  const int64_t M = gids.size(0);
  {
    const S* pm = means.data_ptr<S>();
    const S* pq = quats.data_ptr<S>();
    const S* pl = log_scales.data_ptr<S>();
    const S* po = logits.data_ptr<S>();
    const int64_t* pid = gids.data_ptr<int64_t>();
    const S* gm2 = g_means2d.data_ptr<S>();
    const S* gcn = g_conics.data_ptr<S>();
    const S* gdp = g_depths.data_ptr<S>();
    const S* gop = g_opac.data_ptr<S>();
    S* om = g_means.data_ptr<S>();
    S* oq = g_quats.data_ptr<S>();
    S* ol = g_ls.data_ptr<S>();
    S* oo = g_logits.data_ptr<S>();
    const int64_t n_blocks = (M + kViewBlock - 1) / kViewBlock;
    // [blocks, 12]: dL/dR (row-major) then dL/dt, in double: a sum over up to millions
    std::vector<double> partial(need_viewmat ? n_blocks * 12 : 0, 0.0);
    const S* R = cm.R;
#pragma omp parallel for schedule(dynamic, 1) num_threads(nt)
    for (int64_t blk = 0; blk < n_blocks; ++blk) {
      double acc[12] = {0};
      const int64_t k1 = std::min(M, (blk + 1) * kViewBlock);
      for (int64_t k = blk * kViewBlock; k < k1; ++k) {
        const int64_t i = pid[k];
        const S* m = pm + 3 * i;
        Ewa<S> f;
        ewa(cm, m, pq + 4 * i, pl + 3 * i, f);
        const S a = f.a, b = f.b, c = f.c;
        const S det = a * c - b * b;
        const S id2 = S(1) / (det * det);
        const S g0 = gcn[3 * k], g1 = gcn[3 * k + 1], g2 = gcn[3 * k + 2];
        // conic = (c, -b, a) / det
        const S ga = (-c * c * g0 + b * c * g1 - b * b * g2) * id2;
        const S gb = (S(2) * b * c * g0 - (det + S(2) * b * b) * g1 + S(2) * a * b * g2) * id2;
        const S gc = (-b * b * g0 + a * b * g1 - a * a * g2) * id2;
        S gM0[3], gM1[3];
        S* gls = ol + 3 * i;
        for (int j = 0; j < 3; ++j) {
          const S gT0 = S(2) * ga * f.T0[j] + gb * f.T1[j];
          const S gT1 = gb * f.T0[j] + S(2) * gc * f.T1[j];
          gls[j] = (gT0 * f.M0[j] + gT1 * f.M1[j]) * f.s[j];
          gM0[j] = gT0 * f.s[j];
          gM1[j] = gT1 * f.s[j];
        }
        const S* Q = f.Rq;
        S gA0[3], gA1[3], gQ[9];
        for (int k2 = 0; k2 < 3; ++k2) {
          gA0[k2] = gM0[0] * Q[3 * k2] + gM0[1] * Q[3 * k2 + 1] + gM0[2] * Q[3 * k2 + 2];
          gA1[k2] = gM1[0] * Q[3 * k2] + gM1[1] * Q[3 * k2 + 1] + gM1[2] * Q[3 * k2 + 2];
          for (int j = 0; j < 3; ++j) gQ[3 * k2 + j] = f.A0[k2] * gM0[j] + f.A1[k2] * gM1[j];
        }
        // rotation matrix of the normalised quaternion, backward
        const S w = f.q[0], x = f.q[1], y = f.q[2], z = f.q[3];
        S gq[4];
        gq[0] = 2 * (-z * gQ[1] + y * gQ[2] + z * gQ[3] - x * gQ[5] - y * gQ[6] + x * gQ[7]);
        gq[1] = 2 * (y * gQ[1] + z * gQ[2] + y * gQ[3] - 2 * x * gQ[4] - w * gQ[5] +
                     z * gQ[6] + w * gQ[7] - 2 * x * gQ[8]);
        gq[2] = 2 * (-2 * y * gQ[0] + x * gQ[1] + w * gQ[2] + x * gQ[3] + z * gQ[5] -
                     w * gQ[6] + z * gQ[7] - 2 * y * gQ[8]);
        gq[3] = 2 * (-2 * z * gQ[0] - w * gQ[1] + x * gQ[2] + w * gQ[3] - 2 * z * gQ[4] +
                     y * gQ[5] + x * gQ[6] + y * gQ[7]);
        S* gqo = oq + 4 * i;
        if (f.qclamp) {  // the clamped norm is a constant
          for (int j = 0; j < 4; ++j) gqo[j] = gq[j] / f.qn;
        } else {
          const S d = f.q[0] * gq[0] + f.q[1] * gq[1] + f.q[2] * gq[2] + f.q[3] * gq[3];
          for (int j = 0; j < 4; ++j) gqo[j] = (gq[j] - f.q[j] * d) / f.qn;
        }
        // A0 = fx rz R0 - fx tx rz^2 R2,  A1 = fy rz R1 - fy ty rz^2 R2
        const S e0 = gA0[0] * R[0] + gA0[1] * R[1] + gA0[2] * R[2];
        const S e1 = gA1[0] * R[3] + gA1[1] * R[4] + gA1[2] * R[5];
        const S h0 = gA0[0] * R[6] + gA0[1] * R[7] + gA0[2] * R[8];
        const S h1 = gA1[0] * R[6] + gA1[1] * R[7] + gA1[2] * R[8];
        S g_rz = cm.fx * e0 + cm.fy * e1;
        const S g_rz2 = -cm.fx * f.tx * h0 - cm.fy * f.ty * h1;
        const S g_tx = -cm.fx * f.rz2 * h0, g_ty = -cm.fy * f.rz2 * h1;
        g_rz += S(2) * f.rz * g_rz2;
        S gx = 0, gy = 0, gz = 0;
        gz += f.ux * g_tx + f.uy * g_ty;  // t = z * clamp(x / z)
        if (f.inx) {
          const S gu = f.z * g_tx;
          gx += f.rz * gu;
          g_rz += f.x * gu;
        }
        if (f.iny) {
          const S gv = f.z * g_ty;
          gy += f.rz * gv;
          g_rz += f.y * gv;
        }
        const S gmx = gm2[2 * k], gmy = gm2[2 * k + 1];
        gx += cm.fx * f.rz * gmx;
        g_rz += cm.fx * f.x * gmx;
        gy += cm.fy * f.rz * gmy;
        g_rz += cm.fy * f.y * gmy;
        gz += gdp[k] - f.rz * f.rz * g_rz;
        S* gmo = om + 3 * i;
        for (int j = 0; j < 3; ++j) gmo[j] = R[j] * gx + R[3 + j] * gy + R[6 + j] * gz;
        const S op = S(1) / (S(1) + std::exp(-po[i]));
        oo[i] = gop[k] * op * (S(1) - op);
        if (need_viewmat) {
          const S gp[3] = {gx, gy, gz};
          for (int r = 0; r < 3; ++r) {
            for (int j = 0; j < 3; ++j) acc[3 * r + j] += double(gp[r] * m[j]);
            acc[9 + r] += double(gp[r]);
          }
          const S fr = cm.fx * f.rz, fyr = cm.fy * f.rz;
          const S w0 = -cm.fx * f.tx * f.rz2, w1 = -cm.fy * f.ty * f.rz2;
          for (int j = 0; j < 3; ++j) {
            acc[j] += double(fr * gA0[j]);
            acc[3 + j] += double(fyr * gA1[j]);
            acc[6 + j] += double(w0 * gA0[j] + w1 * gA1[j]);
          }
        }
      }
      if (need_viewmat)
        for (int r = 0; r < 12; ++r) partial[12 * blk + r] = acc[r];
    }
    if (need_viewmat) {
      double tot[12] = {0};
      for (int64_t blk = 0; blk < n_blocks; ++blk)
        for (int r = 0; r < 12; ++r) tot[r] += partial[12 * blk + r];
      S* gv = g_view.data_ptr<S>();
      for (int r = 0; r < 3; ++r) {
        for (int j = 0; j < 3; ++j) gv[4 * r + j] = S(tot[3 * r + j]);
        gv[4 * r + 3] = S(tot[9 + r]);
      }
    }
  }
}

std::vector<torch::Tensor> project_backward(
    torch::Tensor means, torch::Tensor quats, torch::Tensor log_scales, torch::Tensor logits,
    torch::Tensor viewmat, torch::Tensor gids, double fx, double fy, double cx, double cy,
    int64_t width, int64_t height, double near, double far, double eps2d,
    torch::Tensor g_means2d, torch::Tensor g_conics, torch::Tensor g_depths,
    torch::Tensor g_opac, bool need_viewmat, int64_t threads) {
  check_gaussians(means, quats, log_scales, logits, viewmat);
  const int64_t N = means.size(0), M = gids.size(0);
  TORCH_CHECK(gids.scalar_type() == torch::kInt64 && gids.is_contiguous(), "ids must be int64");
  g_means2d = g_means2d.contiguous();
  g_conics = g_conics.contiguous();
  g_depths = g_depths.contiguous();
  g_opac = g_opac.contiguous();
  TORCH_CHECK(g_means2d.numel() == 2 * M && g_conics.numel() == 3 * M &&
                  g_depths.numel() == M && g_opac.numel() == M,
              "gradients must match the projected outputs");
  for (const auto* g : {&g_means2d, &g_conics, &g_depths, &g_opac})
    TORCH_CHECK(g->scalar_type() == means.scalar_type(), "gradients must have the inputs' dtype");
  const int nt = threads > 0 ? int(threads) : at::get_num_threads();
  auto fopt = means.options();
  auto g_means = torch::zeros({N, 3}, fopt);
  auto g_quats = torch::zeros({N, 4}, fopt);
  auto g_ls = torch::zeros({N, 3}, fopt);
  auto g_logits = torch::zeros({N}, fopt);
  auto g_view = torch::zeros({4, 4}, fopt);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_backward", [&] {
    const auto cm = make_proj_cam<scalar_t>(viewmat, fx, fy, cx, cy, width, height, near,
                                            far, eps2d);
    project_backward_impl<scalar_t>(means, quats, log_scales, logits, gids, cm, g_means2d,
                                     g_conics, g_depths, g_opac, need_viewmat, nt, g_means,
                                     g_quats, g_ls, g_logits, g_view);
  });
  return {g_means, g_quats, g_ls, g_logits, g_view};
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("composite_forward", &composite_forward,
        "accum [H, W, C], T_final [H, W], last pair index [H, W]");
  m.def("composite_backward", &composite_backward,
        "gradients for means2d, conics, features, opacities");
  m.def("bin_tiles", &bin_tiles, "tile offsets [T + 1] and depth-ordered ids [P]");
  m.def("depth_order", &depth_order, "stable ascending order [M] int64 (radix sort)");
  m.def("project_forward", &project_forward,
        "EWA projection: ids [M], means2d [M, 2], conics [M, 3], depths, opacities, radii");
  m.def("project_backward", &project_backward,
        "gradients for means, quats, log_scales, opacity logits and the viewmat");
}
