// Compiled CPU compositor for 2D Gaussian surfels (gsplat 1.5.3 rules): forward and backward, OpenMP over tiles.
//
// Plain C ABI (no torch headers, so it compiles in seconds); worker/mapping/raster_cpu.py owns every buffer and
// calls these functions through ctypes. Suffix _f32 / _f64 gives the float type.
//
// Inputs are the projected visible surfels (see worker/mapping/raster_projection.py):
//   planes [M,9]   uv planes A, B, C: the pixel centre (x, y) meets the surfel plane at p = x A + y B + C,
//                  (u, v) = (p0 / p2, p1 / p2)
//   rays   [M,9]   ray transform T (rows T0, T1, T2); only used to bound where a surfel can reach alpha >= 1/255
//   means2d [M,2]  conic centre (low-pass filter centre), opacities [M], features [M,F] (composited channels),
//   radii [M,2]    gsplat's per-axis pixel radius (tile binning), order [M]: surfel indices by centre depth (stable).
// Per pixel, front to back: rho = min(u^2 + v^2, 2 |x - c|^2), alpha = min(0.999, o exp(-rho / 2)), skip
// alpha < 1/255, stop before a surfel whose next T would be <= 1e-4; out = sum alpha T f, T_final kept with the
// number of list entries up to the last contributor. The backward pass walks each pixel's list back to front,
// recovering T by division (as gsplat does), and writes per-(tile, surfel) gradients that are then summed per
// surfel in a fixed order (deterministic).

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

constexpr int kTile = 16;
constexpr int kTilePixels = kTile * kTile;

// Tile lists: tile t holds pair_surfel[tile_offsets[t] .. tile_offsets[t+1]) front to back; surfel i's pairs are
// surfel_pairs[surfel_offsets[i] .. surfel_offsets[i+1]).
struct Binning {
    int tiles_x, tiles_y;
    const int64_t* tile_offsets;
    const int32_t* pair_surfel;
    const int64_t* surfel_offsets;
    const int64_t* surfel_pairs;
};

int tiles_along(int n) { return (n + kTile - 1) / kTile; }

template <typename scalar_t>
void tile_rect(const scalar_t* means2d, const int32_t* radii, int64_t i, int tiles_x, int tiles_y, int* r) {
    // gsplat: floor((c - r) / ts) .. ceil((c + r) / ts), clamped to the grid; same arithmetic as raster_tiles.py
    const scalar_t cx = means2d[2 * i] / scalar_t(kTile), cy = means2d[2 * i + 1] / scalar_t(kTile);
    const scalar_t rx = scalar_t(radii[2 * i]) / scalar_t(kTile), ry = scalar_t(radii[2 * i + 1]) / scalar_t(kTile);
    auto clampi = [](double v, int hi) { return int(std::min<double>(std::max<double>(v, 0.0), hi)); };
    r[0] = clampi(std::floor(cx - rx), tiles_x);
    r[1] = clampi(std::floor(cy - ry), tiles_y);
    r[2] = clampi(std::ceil(cx + rx), tiles_x);
    r[3] = clampi(std::ceil(cy + ry), tiles_y);
}

// Counts pairs per tile and per surfel into prefix sums tile_offsets [tiles+1], surfel_offsets [M+1]; returns P.
template <typename scalar_t>
int64_t bin_count(const scalar_t* means2d, const int32_t* radii, int64_t M, int W, int H, int64_t* tile_offsets,
                  int64_t* surfel_offsets) {
    const int tx_n = tiles_along(W), ty_n = tiles_along(H);
    const int64_t n_tiles = int64_t(tx_n) * ty_n;
    std::fill(tile_offsets, tile_offsets + n_tiles + 1, 0);
    surfel_offsets[0] = 0;
    for (int64_t i = 0; i < M; ++i) {
        int r[4];
        tile_rect(means2d, radii, i, tx_n, ty_n, r);
        surfel_offsets[i + 1] = surfel_offsets[i] + int64_t(std::max(0, r[2] - r[0])) * std::max(0, r[3] - r[1]);
        for (int ty = r[1]; ty < r[3]; ++ty)
            for (int tx = r[0]; tx < r[2]; ++tx) tile_offsets[int64_t(ty) * tx_n + tx + 1]++;
    }
    for (int64_t t = 0; t < n_tiles; ++t) tile_offsets[t + 1] += tile_offsets[t];
    return tile_offsets[n_tiles];
}

// Fills the tile lists walking the surfels front to back (order), so every list comes out depth-ordered.
template <typename scalar_t>
void bin_fill(const scalar_t* means2d, const int32_t* radii, const int64_t* order, int64_t M, int W, int H,
              const int64_t* tile_offsets, const int64_t* surfel_offsets, int32_t* pair_surfel,
              int64_t* surfel_pairs) {
    const int tx_n = tiles_along(W), ty_n = tiles_along(H);
    std::vector<int64_t> cursor(tile_offsets, tile_offsets + int64_t(tx_n) * ty_n);
    std::vector<int64_t> surfel_cursor(surfel_offsets, surfel_offsets + M);
    for (int64_t k = 0; k < M; ++k) {
        const int64_t i = order[k];
        int r[4];
        tile_rect(means2d, radii, i, tx_n, ty_n, r);
        for (int ty = r[1]; ty < r[3]; ++ty)
            for (int tx = r[0]; tx < r[2]; ++tx) {
                const int64_t pos = cursor[int64_t(ty) * tx_n + tx]++;
                pair_surfel[pos] = int32_t(i);
                surfel_pairs[surfel_cursor[i]++] = pos;
            }
    }
}

// Pixel rectangle [x0, x1) x [y0, y1) outside which alpha < 1/255 for sure (conservative by a 1 px margin):
// the bounding box of the disc u^2 + v^2 <= R^2 (R^2 = 2 ln(255 o)) when the disc is wholly in front of the
// camera, united with the low-pass disc 2 |x - c|^2 <= R^2. Unbounded (whole image) otherwise.
template <typename scalar_t>
void reach_rect(const scalar_t* T, const scalar_t* c, scalar_t opacity, int W, int H, int32_t* out) {
    const double o = double(opacity);
    if (!(o >= 1.0 / 255.0)) {
        out[0] = out[1] = out[2] = out[3] = 0;
        return;
    }
    const double R2 = 2.0 * std::log(255.0 * o) * (1.0 + 1e-4) + 1e-4;
    const double lp = std::sqrt(R2 / 2.0);
    double xmin = double(c[0]) - lp, xmax = double(c[0]) + lp, ymin = double(c[1]) - lp, ymax = double(c[1]) + lp;
    const double t20 = T[6], t21 = T[7], t22 = T[8];
    const double lateral = R2 * (t20 * t20 + t21 * t21);
    const double d = lateral - t22 * t22;
    if (d < -1e-6 * (lateral + t22 * t22)) {
        const double f0 = R2 / d, f2 = -1.0 / d;
        const double cx = f0 * (T[0] * t20 + T[1] * t21) + f2 * T[2] * t22;
        const double cy = f0 * (T[3] * t20 + T[4] * t21) + f2 * T[5] * t22;
        const double hx = std::sqrt(std::max(0.0, cx * cx - (f0 * (T[0] * T[0] + T[1] * T[1]) + f2 * T[2] * T[2])));
        const double hy = std::sqrt(std::max(0.0, cy * cy - (f0 * (T[3] * T[3] + T[4] * T[4]) + f2 * T[5] * T[5])));
        xmin = std::min(xmin, cx - hx);
        xmax = std::max(xmax, cx + hx);
        ymin = std::min(ymin, cy - hy);
        ymax = std::max(ymax, cy + hy);
    } else {
        xmin = ymin = -1e30;
        xmax = ymax = 1e30;
    }
    constexpr double margin = 0.01;  // pixels; covers rounding only (the bounds are exact)
    auto lo = [](double v, int n) { return int(std::min<double>(std::max<double>(std::ceil(v - 0.5), 0.0), n)); };
    auto hi = [](double v, int n) { return int(std::min<double>(std::max<double>(std::floor(v - 0.5) + 1, 0.0), n)); };
    out[0] = lo(xmin - margin, W);
    out[1] = lo(ymin - margin, H);
    out[2] = hi(xmax + margin, W);
    out[3] = hi(ymax + margin, H);
}

template <typename scalar_t>
void reach_rects(const scalar_t* rays, const scalar_t* means2d, const scalar_t* opac, int64_t M, int W, int H,
                 int threads, int32_t* rects) {
#pragma omp parallel for num_threads(threads) schedule(static)
    for (int64_t i = 0; i < M; ++i) reach_rect(rays + 9 * i, means2d + 2 * i, opac[i], W, H, rects + 4 * i);
}

// Everything the per-pixel maths needs for one surfel.
template <typename scalar_t>
struct SurfelView {
    scalar_t A[3], B[3], C[3], cx, cy, o, rho_cut;

    void load(const scalar_t* planes, const scalar_t* means2d, const scalar_t* opac, int64_t g) {
        for (int j = 0; j < 3; ++j) {
            A[j] = planes[9 * g + j];
            B[j] = planes[9 * g + 3 + j];
            C[j] = planes[9 * g + 6 + j];
        }
        cx = means2d[2 * g];
        cy = means2d[2 * g + 1];
        o = opac[g];
        // rho above this cannot give alpha >= 1/255 (small slack; the exact test follows)
        rho_cut = o > scalar_t(0) ? scalar_t(2.0 * std::log(255.0 * double(o)) * (1.0 + 1e-4) + 1e-4) : scalar_t(-1);
    }
};

// The quantities of one (surfel, pixel) evaluation the backward pass needs.
template <typename scalar_t>
struct Hit {
    scalar_t p[3], u, v, rho3, dx, dy, rho2, G, alpha;
    bool use3d;
};

template <typename scalar_t>
inline bool evaluate(const SurfelView<scalar_t>& s, scalar_t x, scalar_t y, Hit<scalar_t>& h) {
    h.dx = x - s.cx;
    h.dy = y - s.cy;
    h.rho2 = scalar_t(2) * (h.dx * h.dx + h.dy * h.dy);
    h.p[0] = x * s.A[0] + y * s.B[0] + s.C[0];
    h.p[1] = x * s.A[1] + y * s.B[1] + s.C[1];
    h.p[2] = x * s.A[2] + y * s.B[2] + s.C[2];
    if (h.p[2] == scalar_t(0)) return false;
    // cheap rejection (no division, no exp): both rho's beyond the cut, rho3 > cut <=> p0^2 + p1^2 > cut p2^2
    if (h.rho2 > s.rho_cut && h.p[0] * h.p[0] + h.p[1] * h.p[1] > s.rho_cut * h.p[2] * h.p[2]) return false;
    h.u = h.p[0] / h.p[2];
    h.v = h.p[1] / h.p[2];
    h.rho3 = h.u * h.u + h.v * h.v;
    h.use3d = h.rho3 <= h.rho2;
    const scalar_t rho = h.use3d ? h.rho3 : h.rho2;
    h.G = std::exp(scalar_t(-0.5) * rho);
    h.alpha = std::min(scalar_t(0.999), s.o * h.G);
    return h.alpha >= scalar_t(1.0 / 255.0);
}

template <typename scalar_t>
void forward_impl(const Binning& b, const int32_t* rects, const scalar_t* planes, const scalar_t* means2d,
                  const scalar_t* opac, const scalar_t* feats, int F, int W, int H, int threads, scalar_t* out_feat,
                  scalar_t* out_T, int32_t* out_count) {
    const int64_t n_tiles = int64_t(b.tiles_x) * b.tiles_y;
#pragma omp parallel num_threads(threads)
    {
        std::vector<scalar_t> T(kTilePixels), acc(kTilePixels * F);
        std::vector<int32_t> count(kTilePixels);
        std::vector<char> done(kTilePixels);
#pragma omp for schedule(dynamic, 1)
        for (int64_t t = 0; t < n_tiles; ++t) {
            const int x0 = int(t % b.tiles_x) * kTile, y0 = int(t / b.tiles_x) * kTile;
            const int tw = std::min(kTile, W - x0), th = std::min(kTile, H - y0);
            std::fill(T.begin(), T.end(), scalar_t(1));
            std::fill(acc.begin(), acc.end(), scalar_t(0));
            std::fill(count.begin(), count.end(), 0);
            std::fill(done.begin(), done.end(), 0);
            int remaining = tw * th;
            const int64_t start = b.tile_offsets[t], end = b.tile_offsets[t + 1];
            for (int64_t k = start; k < end && remaining > 0; ++k) {
                const int64_t g = b.pair_surfel[k];
                const int32_t* r = rects + 4 * g;
                const int ys = std::max(r[1], y0), ye = std::min(r[3], y0 + th);
                const int xs = std::max(r[0], x0), xe = std::min(r[2], x0 + tw);
                if (ys >= ye || xs >= xe) continue;
                SurfelView<scalar_t> s;
                s.load(planes, means2d, opac, g);
                const scalar_t* f = feats + int64_t(F) * g;
                Hit<scalar_t> h;
                for (int py = ys; py < ye; ++py) {
                    const scalar_t y = scalar_t(py) + scalar_t(0.5);
                    for (int px = xs; px < xe; ++px) {
                        const int l = (py - y0) * kTile + (px - x0);
                        if (done[l]) continue;
                        if (!evaluate(s, scalar_t(px) + scalar_t(0.5), y, h)) continue;
                        const scalar_t next_T = T[l] * (scalar_t(1) - h.alpha);
                        if (next_T <= scalar_t(1e-4)) {
                            done[l] = 1;
                            --remaining;
                            continue;
                        }
                        const scalar_t w = h.alpha * T[l];
                        scalar_t* a = &acc[l * F];
                        for (int c = 0; c < F; ++c) a[c] += w * f[c];
                        T[l] = next_T;
                        count[l] = int32_t(k - start + 1);
                    }
                }
            }
            for (int ly = 0; ly < th; ++ly)
                for (int lx = 0; lx < tw; ++lx) {
                    const int l = ly * kTile + lx;
                    const int64_t pix = int64_t(y0 + ly) * W + (x0 + lx);
                    out_T[pix] = T[l];
                    out_count[pix] = count[l];
                    for (int c = 0; c < F; ++c) out_feat[pix * F + c] = acc[l * F + c];
                }
        }
    }
}

// Per-pair gradient layout: dA(3) dB(3) dC(3) dmeans2d(2) dopacity(1) dfeatures(F)
constexpr int kPairFixed = 12;

template <typename scalar_t>
void backward_impl(const Binning& b, const int32_t* rects, const scalar_t* planes, const scalar_t* means2d,
                   const scalar_t* opac, const scalar_t* feats, int F, int W, int H, int threads,
                   const scalar_t* T_final, const int32_t* counts, const scalar_t* g_feat, const scalar_t* g_alpha,
                   scalar_t* pair_grads) {
    const int64_t n_tiles = int64_t(b.tiles_x) * b.tiles_y;
    const int stride = kPairFixed + F;
#pragma omp parallel num_threads(threads)
    {
        // transmittance bookkeeping in double: T is recovered by repeated division, S by a long sum
        std::vector<double> T(kTilePixels), S(kTilePixels), Tf(kTilePixels), gA(kTilePixels);
        std::vector<scalar_t> gf(kTilePixels * F);
        std::vector<int32_t> count(kTilePixels);
        std::vector<double> acc(stride);
#pragma omp for schedule(dynamic, 1)
        for (int64_t t = 0; t < n_tiles; ++t) {
            const int x0 = int(t % b.tiles_x) * kTile, y0 = int(t / b.tiles_x) * kTile;
            const int tw = std::min(kTile, W - x0), th = std::min(kTile, H - y0);
            int max_count = 0;
            std::fill(count.begin(), count.end(), 0);
            for (int ly = 0; ly < th; ++ly)
                for (int lx = 0; lx < tw; ++lx) {
                    const int l = ly * kTile + lx;
                    const int64_t pix = int64_t(y0 + ly) * W + (x0 + lx);
                    T[l] = Tf[l] = T_final[pix];
                    S[l] = 0.0;
                    gA[l] = g_alpha[pix];
                    count[l] = counts[pix];
                    max_count = std::max(max_count, int(counts[pix]));
                    for (int c = 0; c < F; ++c) gf[l * F + c] = g_feat[pix * F + c];
                }
            const int64_t start = b.tile_offsets[t];
            for (int64_t k = start + max_count - 1; k >= start; --k) {
                const int64_t g = b.pair_surfel[k];
                const int32_t* r = rects + 4 * g;
                const int ys = std::max(r[1], y0), ye = std::min(r[3], y0 + th);
                const int xs = std::max(r[0], x0), xe = std::min(r[2], x0 + tw);
                if (ys >= ye || xs >= xe) continue;
                SurfelView<scalar_t> s;
                s.load(planes, means2d, opac, g);
                const scalar_t* f = feats + int64_t(F) * g;
                std::fill(acc.begin(), acc.end(), 0.0);
                bool touched = false;
                Hit<scalar_t> h;
                const int32_t rank = int32_t(k - start);
                for (int py = ys; py < ye; ++py) {
                    const scalar_t y = scalar_t(py) + scalar_t(0.5);
                    for (int px = xs; px < xe; ++px) {
                        const int l = (py - y0) * kTile + (px - x0);
                        if (rank >= count[l]) continue;
                        const scalar_t x = scalar_t(px) + scalar_t(0.5);
                        if (!evaluate(s, x, y, h)) continue;
                        touched = true;
                        const double keep = 1.0 - double(h.alpha);
                        const double T_i = T[l] / keep;
                        const double w = double(h.alpha) * T_i;
                        const scalar_t* gl = &gf[l * F];
                        double fdot = 0;
                        for (int c = 0; c < F; ++c) {
                            fdot += double(gl[c]) * double(f[c]);
                            acc[kPairFixed + c] += w * double(gl[c]);
                        }
                        const scalar_t d_alpha = scalar_t(T_i * fdot - (S[l] - gA[l] * Tf[l]) / keep);
                        S[l] += w * fdot;
                        T[l] = T_i;
                        if (s.o * h.G > scalar_t(0.999)) continue;  // clamped alpha: no gradient (as in gsplat)
                        acc[11] += double(d_alpha * h.G);
                        const scalar_t d_rho = scalar_t(-0.5) * h.G * s.o * d_alpha;
                        if (h.use3d) {
                            const scalar_t inv = scalar_t(1) / h.p[2];
                            const scalar_t du = scalar_t(2) * h.u * d_rho, dv = scalar_t(2) * h.v * d_rho;
                            const scalar_t dp0 = du * inv, dp1 = dv * inv, dp2 = -(du * h.u + dv * h.v) * inv;
                            acc[0] += double(x * dp0);
                            acc[1] += double(x * dp1);
                            acc[2] += double(x * dp2);
                            acc[3] += double(y * dp0);
                            acc[4] += double(y * dp1);
                            acc[5] += double(y * dp2);
                            acc[6] += double(dp0);
                            acc[7] += double(dp1);
                            acc[8] += double(dp2);
                        } else {
                            acc[9] += double(scalar_t(-4) * h.dx * d_rho);
                            acc[10] += double(scalar_t(-4) * h.dy * d_rho);
                        }
                    }
                }
                scalar_t* out = pair_grads + k * stride;
                if (touched)
                    for (int j = 0; j < stride; ++j) out[j] = scalar_t(acc[j]);
            }
        }
    }
}

// Sum every surfel's pair gradients (parallel over surfels, fixed order: deterministic).
template <typename scalar_t>
void reduce_pairs(const Binning& b, const scalar_t* pair_grads, int F, int64_t M, int threads, scalar_t* d_planes,
                  scalar_t* d_means2d, scalar_t* d_opac, scalar_t* d_feats) {
    const int stride = kPairFixed + F;
#pragma omp parallel num_threads(threads)
    {
        std::vector<double> sum(stride);
#pragma omp for schedule(static)
        for (int64_t i = 0; i < M; ++i) {
            std::fill(sum.begin(), sum.end(), 0.0);
            for (int64_t j = b.surfel_offsets[i]; j < b.surfel_offsets[i + 1]; ++j) {
                const scalar_t* row = pair_grads + b.surfel_pairs[j] * stride;
                for (int c = 0; c < stride; ++c) sum[c] += double(row[c]);
            }
            for (int c = 0; c < 9; ++c) d_planes[9 * i + c] = scalar_t(sum[c]);
            d_means2d[2 * i] = scalar_t(sum[9]);
            d_means2d[2 * i + 1] = scalar_t(sum[10]);
            d_opac[i] = scalar_t(sum[11]);
            for (int c = 0; c < F; ++c) d_feats[int64_t(F) * i + c] = scalar_t(sum[kPairFixed + c]);
        }
    }
}


}  // namespace

#define RASTER_CPU_API(SUFFIX, T)                                                                                   \
    extern "C" int64_t raster_bin_count_##SUFFIX(const T* means2d, const int32_t* radii, int64_t M, int W, int H,  \
                                                 int64_t* tile_offsets, int64_t* surfel_offsets) {                \
        return bin_count(means2d, radii, M, W, H, tile_offsets, surfel_offsets);                                   \
    }                                                                                                              \
    extern "C" void raster_bin_fill_##SUFFIX(const T* means2d, const int32_t* radii, const int64_t* order,          \
                                             int64_t M, int W, int H, const int64_t* tile_offsets,                 \
                                             const int64_t* surfel_offsets, int32_t* pair_surfel,                  \
                                             int64_t* surfel_pairs) {                                              \
        bin_fill(means2d, radii, order, M, W, H, tile_offsets, surfel_offsets, pair_surfel, surfel_pairs);         \
    }                                                                                                              \
    extern "C" void raster_reach_rects_##SUFFIX(const T* rays, const T* means2d, const T* opac, int64_t M, int W,  \
                                                int H, int threads, int32_t* rects) {                              \
        reach_rects(rays, means2d, opac, M, W, H, threads, rects);                                                 \
    }                                                                                                              \
    extern "C" void raster_forward_##SUFFIX(const int64_t* tile_offsets, const int32_t* pair_surfel,               \
                                            const int32_t* rects, const T* planes, const T* means2d, const T* opac, \
                                            const T* feats, int F, int W, int H, int threads, T* out_feat,         \
                                            T* out_T, int32_t* out_count) {                                        \
        const Binning b{tiles_along(W), tiles_along(H), tile_offsets, pair_surfel, nullptr, nullptr};             \
        forward_impl(b, rects, planes, means2d, opac, feats, F, W, H, threads, out_feat, out_T, out_count);        \
    }                                                                                                              \
    extern "C" void raster_backward_##SUFFIX(                                                                      \
        const int64_t* tile_offsets, const int32_t* pair_surfel, const int64_t* surfel_offsets,                    \
        const int64_t* surfel_pairs, const int32_t* rects, const T* planes, const T* means2d, const T* opac,       \
        const T* feats, int64_t M, int F, int W, int H, int threads, const T* T_final, const int32_t* counts,      \
        const T* g_feat, const T* g_alpha, T* pair_grads, T* d_planes, T* d_means2d, T* d_opac, T* d_feats) {      \
        const Binning b{tiles_along(W), tiles_along(H), tile_offsets, pair_surfel, surfel_offsets, surfel_pairs};  \
        backward_impl(b, rects, planes, means2d, opac, feats, F, W, H, threads, T_final, counts, g_feat, g_alpha,  \
                      pair_grads);                                                                                 \
        reduce_pairs(b, pair_grads, F, M, threads, d_planes, d_means2d, d_opac, d_feats);                          \
    }

RASTER_CPU_API(f32, float)
RASTER_CPU_API(f64, double)
