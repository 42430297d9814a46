// Compiled CPU rasterizer for 2D Gaussian surfels (gsplat 1.5.3 rules): projection, tile binning, compositing,
// and the backward of all three, on worker threads (see run_workers).
//
// Plain C ABI (no torch headers, so it compiles in seconds); worker/mapping/raster_cpu.py owns every buffer and
// calls these functions through ctypes. Suffix _f32 / _f64 gives the float type.
//
// Projection (per surfel, float64 internally; see worker/mapping/raster_projection.py for the torch twin):
//   mu_c = R_cw mu + t, R_c = R_cw R(q / |q|), T = K [s_u R_c[:,0] | s_v R_c[:,1] | mu_c] (rows T0, T1, T2),
//   uv planes A = T1 x T2, B = T2 x T0, C = T0 x T1 (pixel centre (x, y) meets the surfel plane at
//   p = x A + y B + C, (u, v) = (p0 / p2, p1 / p2)), centre c and half extents h of the r = 1 conic's bounding box,
//   radius ceil(3.33 h) per axis, depth T22, camera-frame normal R_c[:,2] flipped towards the camera. Culled (radius
//   0): centre depth outside (0.01, 1e10), degenerate conic, box off-screen.
// Per-surfel arrays keep all N input surfels (culled ones are simply never binned):
//   planes [N,9], rays [N,9] (T, optional output; composite_cpu bounds the reach rectangles with it), means2d [N,2],
//   depths [N], opacities [N], features [N,F] (composited channels), radii [N,2], rects [N,4] (reach rectangles).
// Compositing, per pixel front to back (by centre depth, ties by index): rho = min(u^2 + v^2, 2 |x - c|^2),
// alpha = min(0.999, o exp(-rho / 2)), skip alpha < 1/255, stop before a surfel whose next T would be <= 1e-4;
// out = sum alpha T f, T_final kept with the number of list entries up to the last contributor. The backward pass
// walks each pixel's list back to front, recovering T by division (as gsplat does), and writes per-(tile, surfel)
// gradients that are then summed per surfel in a fixed order (deterministic for any thread count).

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <thread>
#include <vector>

namespace {

constexpr int kTile = 16;
constexpr int kTilePixels = kTile * kTile;
constexpr double kNearPlane = 0.01;
constexpr double kFarPlane = 1e10;
constexpr double kRadiusSigmas = 3.33;
constexpr int kProjectedFeatures = 7;  // colour (3), depth, camera-frame normal (3)

int tiles_along(int n) {
    return (n + kTile - 1) / kTile;
}

// Work sharing: consecutive index ranges of `grain` handed out once each until [0, n) is used up.
class Ranges {
  public:
    Ranges(int64_t n, int64_t grain) : n_(n), grain_(std::max<int64_t>(1, grain)) {}
    bool claim(int64_t& begin, int64_t& end) {
        begin = next_.fetch_add(grain_, std::memory_order_relaxed);
        if (begin >= n_) return false;
        end = std::min(n_, begin + grain_);
        return true;
    }
    int64_t chunks() const { return (n_ + grain_ - 1) / grain_; }

  private:
    std::atomic<int64_t> next_{0};
    const int64_t n_, grain_;
};

// Runs worker(ranges) on `threads` threads (the caller and threads - 1 std::threads) over [0, n). Not OpenMP on
// purpose: idle workers wait passively (join), where OpenMP's spinning workers, on a machine whose cores are busy
// with other processes, take the cores from the ones still working (measured: 2 threads 3-6x slower than 1).
template <typename Worker>
void run_workers(int threads, int64_t n, int64_t grain, Worker worker) {
    Ranges ranges(n, grain);
    const int64_t extra = std::max<int64_t>(0, std::min<int64_t>(threads, ranges.chunks()) - 1);
    std::vector<std::thread> pool;
    pool.reserve(size_t(extra));
    for (int64_t i = 0; i < extra; ++i) pool.emplace_back([&ranges, &worker] { worker(ranges); });
    worker(ranges);
    for (std::thread& t : pool) t.join();
}

// ---------------------------------------------------------------------------------------------------------------
// Projection

struct Camera {
    double R[9], t[3], K[9];  // world -> camera rotation and translation (row-major), intrinsics
};

template <typename scalar_t>
Camera load_camera(const scalar_t* viewmat, const scalar_t* K) {
    Camera cam;
    for (int r = 0; r < 3; ++r) {
        for (int j = 0; j < 3; ++j) {
            cam.R[3 * r + j] = viewmat[4 * r + j];
            cam.K[3 * r + j] = K[3 * r + j];
        }
        cam.t[r] = viewmat[4 * r + 3];
    }
    return cam;
}

// One surfel's projection in float64; the backward pass recomputes it instead of storing it.
struct Projection {
    double q[4], q_norm;  // unit quaternion (wxyz) and the clamped norm it was divided by
    bool q_clamped;       // |q| < 1e-12: the norm is a constant (no gradient through it)
    double Rq[9];         // surfel rotation (world)
    double Rc[9];         // camera-frame rotation R_cw Rq
    double mc[3];         // camera-frame centre
    double su, sv;
    double T[9];  // ray transform, rows T0, T1, T2
    double d, cx, cy, hx2, hy2;
    double facing;  // +1 when the normal R_c[:,2] already faces the camera, else -1
};

inline void rotmat_from_unit_quat(const double* q, double* R) {
    const double w = q[0], x = q[1], y = q[2], z = q[3];
    R[0] = 1 - 2 * (y * y + z * z), R[1] = 2 * (x * y - w * z), R[2] = 2 * (x * z + w * y);
    R[3] = 2 * (x * y + w * z), R[4] = 1 - 2 * (x * x + z * z), R[5] = 2 * (y * z - w * x);
    R[6] = 2 * (x * z - w * y), R[7] = 2 * (y * z + w * x), R[8] = 1 - 2 * (x * x + y * y);
}

// Fills p; false when the surfel is culled by depth or has a degenerate conic (screen bounds are checked apart).
template <typename scalar_t>
bool project_one(const Camera& cam, const scalar_t* mu, const scalar_t* quat, const scalar_t* scale, Projection& p) {
    for (int r = 0; r < 3; ++r)
        p.mc[r] = cam.R[3 * r] * double(mu[0]) + cam.R[3 * r + 1] * double(mu[1]) + cam.R[3 * r + 2] * double(mu[2]) +
                  cam.t[r];
    if (!(p.mc[2] > kNearPlane && p.mc[2] < kFarPlane)) return false;
    const double n = std::sqrt(double(quat[0]) * quat[0] + double(quat[1]) * quat[1] + double(quat[2]) * quat[2] +
                               double(quat[3]) * quat[3]);
    p.q_clamped = !(n >= 1e-12);
    p.q_norm = p.q_clamped ? 1e-12 : n;
    for (int j = 0; j < 4; ++j) p.q[j] = double(quat[j]) / p.q_norm;
    rotmat_from_unit_quat(p.q, p.Rq);
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c)
            p.Rc[3 * r + c] = cam.R[3 * r] * p.Rq[c] + cam.R[3 * r + 1] * p.Rq[3 + c] + cam.R[3 * r + 2] * p.Rq[6 + c];
    p.su = scale[0];
    p.sv = scale[1];
    double WH[9];  // columns: s_u R_c[:,0], s_v R_c[:,1], mu_c
    for (int k = 0; k < 3; ++k) {
        WH[3 * k] = p.Rc[3 * k] * p.su;
        WH[3 * k + 1] = p.Rc[3 * k + 1] * p.sv;
        WH[3 * k + 2] = p.mc[k];
    }
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c)
            p.T[3 * r + c] = cam.K[3 * r] * WH[c] + cam.K[3 * r + 1] * WH[3 + c] + cam.K[3 * r + 2] * WH[6 + c];
    const double* T = p.T;
    p.d = T[6] * T[6] + T[7] * T[7] - T[8] * T[8];
    if (p.d == 0.0) return false;
    // tangent lines x T2 - T0 (and y T2 - T1) to the disc u^2 + v^2 = 1, with t = (1, 1, -1)
    p.cx = (T[0] * T[6] + T[1] * T[7] - T[2] * T[8]) / p.d;
    p.cy = (T[3] * T[6] + T[4] * T[7] - T[5] * T[8]) / p.d;
    p.hx2 = p.cx * p.cx - (T[0] * T[0] + T[1] * T[1] - T[2] * T[2]) / p.d;
    p.hy2 = p.cy * p.cy - (T[3] * T[3] + T[4] * T[4] - T[5] * T[5]) / p.d;
    p.facing = (p.Rc[2] * p.mc[0] + p.Rc[5] * p.mc[1] + p.Rc[8] * p.mc[2]) < 0 ? 1.0 : -1.0;
    return true;
}

inline void cross3(const double* a, const double* b, double* out) {
    out[0] = a[1] * b[2] - a[2] * b[1];
    out[1] = a[2] * b[0] - a[0] * b[2];
    out[2] = a[0] * b[1] - a[1] * b[0];
}

// Pixel rectangle [x0, x1) x [y0, y1) outside which alpha < 1/255 for sure: the bounding box of the disc
// u^2 + v^2 <= R^2 (R^2 = 2 ln(255 o)) when the disc is wholly in front of the camera, united with the low-pass disc
// 2 |x - c|^2 <= R^2. Unbounded (whole image) otherwise.
inline void reach_rect(const double* T, double cx0, double cy0, double o, int W, int H, int32_t* out) {
    if (!(o >= 1.0 / 255.0)) {
        out[0] = out[1] = out[2] = out[3] = 0;
        return;
    }
    const double R2 = 2.0 * std::log(255.0 * o) * (1.0 + 1e-4) + 1e-4;
    const double lp = std::sqrt(R2 / 2.0);
    double xmin = cx0 - lp, xmax = cx0 + lp, ymin = cy0 - lp, ymax = cy0 + lp;
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
void project(int64_t N, const scalar_t* means, const scalar_t* quats, const scalar_t* scales, const scalar_t* opac,
             const scalar_t* colors, const scalar_t* viewmat, const scalar_t* K, int W, int H, int threads,
             scalar_t* rays, scalar_t* planes, scalar_t* means2d, scalar_t* depths, scalar_t* feats, int32_t* radii,
             int32_t* rects) {
    const Camera cam = load_camera(viewmat, K);
    constexpr int F = kProjectedFeatures;
    run_workers(threads, N, 1024, [&](Ranges& ranges) {
        for (int64_t lo, hi; ranges.claim(lo, hi);)
            for (int64_t i = lo; i < hi; ++i) {
                Projection p;
                bool visible = project_one(cam, means + 3 * i, quats + 4 * i, scales + 2 * i, p);
                double rx = 0, ry = 0;
                if (visible) {
                    rx = std::ceil(kRadiusSigmas * std::sqrt(std::max(p.hx2, 1e-4)));
                    ry = std::ceil(kRadiusSigmas * std::sqrt(std::max(p.hy2, 1e-4)));
                    visible = p.cx + rx > 0 && p.cx - rx < W && p.cy + ry > 0 && p.cy - ry < H;
                }
                if (!visible) {
                    if (rays) std::fill(rays + 9 * i, rays + 9 * i + 9, scalar_t(0));
                    std::fill(planes + 9 * i, planes + 9 * i + 9, scalar_t(0));
                    std::fill(feats + F * i, feats + F * i + F, scalar_t(0));
                    means2d[2 * i] = means2d[2 * i + 1] = depths[i] = scalar_t(0);
                    radii[2 * i] = radii[2 * i + 1] = 0;
                    std::fill(rects + 4 * i, rects + 4 * i + 4, 0);
                    continue;
                }
                const double* T = p.T;
                double A[3], B[3], C[3];
                cross3(T + 3, T + 6, A);
                cross3(T + 6, T, B);
                cross3(T, T + 3, C);
                for (int j = 0; j < 3; ++j) {
                    planes[9 * i + j] = scalar_t(A[j]);
                    planes[9 * i + 3 + j] = scalar_t(B[j]);
                    planes[9 * i + 6 + j] = scalar_t(C[j]);
                }
                if (rays)
                    for (int j = 0; j < 9; ++j) rays[9 * i + j] = scalar_t(T[j]);
                means2d[2 * i] = scalar_t(p.cx);
                means2d[2 * i + 1] = scalar_t(p.cy);
                depths[i] = scalar_t(T[8]);
                scalar_t* f = feats + F * i;
                for (int j = 0; j < 3; ++j) {
                    f[j] = colors[3 * i + j];
                    f[4 + j] = scalar_t(p.Rc[3 * j + 2] * p.facing);
                }
                f[3] = scalar_t(T[8]);
                radii[2 * i] = int32_t(rx);
                radii[2 * i + 1] = int32_t(ry);
                reach_rect(T, double(means2d[2 * i]), double(means2d[2 * i + 1]), double(opac[i]), W, H, rects + 4 * i);
            }
    });
}

// Chain rule from the projected quantities' gradients (uv planes, means2d, features) to means, quats, scales, colours
// and the view matrix. Culled surfels get zero gradients. The view matrix gradient is summed over fixed blocks of
// surfels, then over blocks in order: deterministic for any thread count.
template <typename scalar_t>
void project_backward(int64_t N, const scalar_t* means, const scalar_t* quats, const scalar_t* scales,
                      const scalar_t* viewmat, const scalar_t* K, const int32_t* radii, const scalar_t* d_planes,
                      const scalar_t* d_means2d, const scalar_t* d_feats, int threads, scalar_t* d_means,
                      scalar_t* d_quats, scalar_t* d_scales, scalar_t* d_colors, scalar_t* d_viewmat) {
    const Camera cam = load_camera(viewmat, K);
    constexpr int F = kProjectedFeatures;
    constexpr int64_t kBlock = 1024;
    const int64_t n_blocks = (N + kBlock - 1) / kBlock;
    std::vector<double> block_dV(n_blocks * 12, 0.0);  // per block: d R_cw (9, row-major), d t (3)
    run_workers(threads, n_blocks, 4, [&](Ranges& ranges) {
        for (int64_t lo, hi; ranges.claim(lo, hi);)
            for (int64_t b = lo; b < hi; ++b) {
                double* dV = &block_dV[12 * b];
                for (int64_t i = b * kBlock; i < std::min(N, (b + 1) * kBlock); ++i) {
                    for (int j = 0; j < 3; ++j) d_colors[3 * i + j] = d_feats[F * i + j];
                    Projection p;
                    if (radii[2 * i] <= 0 || !project_one(cam, means + 3 * i, quats + 4 * i, scales + 2 * i, p)) {
                        std::fill(d_means + 3 * i, d_means + 3 * i + 3, scalar_t(0));
                        std::fill(d_quats + 4 * i, d_quats + 4 * i + 4, scalar_t(0));
                        std::fill(d_scales + 2 * i, d_scales + 2 * i + 2, scalar_t(0));
                        continue;
                    }
                    const double* T = p.T;
                    double gA[3], gB[3], gC[3], tmp[3];
                    for (int j = 0; j < 3; ++j) {
                        gA[j] = d_planes[9 * i + j];
                        gB[j] = d_planes[9 * i + 3 + j];
                        gC[j] = d_planes[9 * i + 6 + j];
                    }
                    double dT[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
                    double* dT0 = dT;
                    double* dT1 = dT + 3;
                    double* dT2 = dT + 6;
                    auto add = [](double* to, const double* v) { to[0] += v[0], to[1] += v[1], to[2] += v[2]; };
                    // c = a x b: dc/da^T g = b x g, dc/db^T g = g x a
                    cross3(T + 6, gA, tmp), add(dT1, tmp);  // A = T1 x T2
                    cross3(gA, T + 3, tmp), add(dT2, tmp);
                    cross3(T, gB, tmp), add(dT2, tmp);  // B = T2 x T0
                    cross3(gB, T + 6, tmp), add(dT0, tmp);
                    cross3(T + 3, gC, tmp), add(dT0, tmp);  // C = T0 x T1
                    cross3(gC, T, tmp), add(dT1, tmp);
                    const double gcx = d_means2d[2 * i], gcy = d_means2d[2 * i + 1];
                    const double sgn[3] = {1.0, 1.0, -1.0};
                    for (int j = 0; j < 3; ++j) {
                        dT0[j] += gcx * sgn[j] * T[6 + j] / p.d;
                        dT1[j] += gcy * sgn[j] * T[6 + j] / p.d;
                        dT2[j] += (gcx * (T[j] - 2 * p.cx * T[6 + j]) + gcy * (T[3 + j] - 2 * p.cy * T[6 + j])) *
                                  sgn[j] / p.d;
                    }
                    dT[8] += d_feats[F * i + 3];  // depth feature = T22
                    double dWH[9];                // K^T dT
                    for (int k = 0; k < 3; ++k)
                        for (int c = 0; c < 3; ++c)
                            dWH[3 * k + c] = cam.K[k] * dT[c] + cam.K[3 + k] * dT[3 + c] + cam.K[6 + k] * dT[6 + c];
                    double dRc[9], dmc[3];
                    double dsu = 0, dsv = 0;
                    for (int k = 0; k < 3; ++k) {
                        dRc[3 * k] = dWH[3 * k] * p.su;
                        dRc[3 * k + 1] = dWH[3 * k + 1] * p.sv;
                        dRc[3 * k + 2] = double(d_feats[F * i + 4 + k]) * p.facing;
                        dsu += dWH[3 * k] * p.Rc[3 * k];
                        dsv += dWH[3 * k + 1] * p.Rc[3 * k + 1];
                        dmc[k] = dWH[3 * k + 2];
                    }
                    const scalar_t* mu = means + 3 * i;
                    for (int j = 0; j < 3; ++j)
                        d_means[3 * i + j] =
                            scalar_t(cam.R[j] * dmc[0] + cam.R[3 + j] * dmc[1] + cam.R[6 + j] * dmc[2]);
                    double G[9];  // d Rq = R_cw^T dRc
                    for (int j = 0; j < 3; ++j)
                        for (int c = 0; c < 3; ++c)
                            G[3 * j + c] = cam.R[j] * dRc[c] + cam.R[3 + j] * dRc[3 + c] + cam.R[6 + j] * dRc[6 + c];
                    for (int k = 0; k < 3; ++k) {
                        for (int j = 0; j < 3; ++j)
                            dV[3 * k + j] += dmc[k] * double(mu[j]) + dRc[3 * k] * p.Rq[3 * j] +
                                             dRc[3 * k + 1] * p.Rq[3 * j + 1] + dRc[3 * k + 2] * p.Rq[3 * j + 2];
                        dV[9 + k] += dmc[k];
                    }
                    const double w = p.q[0], x = p.q[1], y = p.q[2], z = p.q[3];
                    double dq[4];
                    dq[0] = 2 * (-z * G[1] + y * G[2] + z * G[3] - x * G[5] - y * G[6] + x * G[7]);
                    dq[1] = 2 * (y * G[1] + z * G[2] + y * G[3] - 2 * x * G[4] - w * G[5] + z * G[6] + w * G[7] -
                                 2 * x * G[8]);
                    dq[2] = 2 * (-2 * y * G[0] + x * G[1] + w * G[2] + x * G[3] + z * G[5] - w * G[6] + z * G[7] -
                                 2 * y * G[8]);
                    dq[3] = 2 * (-2 * z * G[0] - w * G[1] + x * G[2] + w * G[3] - 2 * z * G[4] + y * G[5] + x * G[6] +
                                 y * G[7]);
                    const double radial = p.q_clamped ? 0.0 : w * dq[0] + x * dq[1] + y * dq[2] + z * dq[3];
                    for (int j = 0; j < 4; ++j) d_quats[4 * i + j] = scalar_t((dq[j] - p.q[j] * radial) / p.q_norm);
                    d_scales[2 * i] = scalar_t(dsu);
                    d_scales[2 * i + 1] = scalar_t(dsv);
                }
            }
    });
    double dV[12] = {0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0};
    for (int64_t b = 0; b < n_blocks; ++b)
        for (int j = 0; j < 12; ++j) dV[j] += block_dV[12 * b + j];
    std::fill(d_viewmat, d_viewmat + 16, scalar_t(0));
    for (int r = 0; r < 3; ++r) {
        for (int j = 0; j < 3; ++j) d_viewmat[4 * r + j] = scalar_t(dV[3 * r + j]);
        d_viewmat[4 * r + 3] = scalar_t(dV[9 + r]);
    }
}

// ---------------------------------------------------------------------------------------------------------------
// Tile binning

// Tile lists: tile t holds pair_surfel[tile_offsets[t] .. tile_offsets[t+1]) front to back; surfel i's pairs are
// surfel_pairs[surfel_offsets[i] .. surfel_offsets[i+1]).
struct Binning {
    int tiles_x, tiles_y;
    const int64_t* tile_offsets;
    const int32_t* pair_surfel;
    const int64_t* surfel_offsets;
    const int64_t* surfel_pairs;
};

// gsplat: floor((c - r) / ts) .. ceil((c + r) / ts), clamped to the grid; same arithmetic as raster_tiles.py.
// A surfel with a zero radius is culled: no tiles.
template <typename scalar_t>
void tile_rect(const scalar_t* means2d, const int32_t* radii, int64_t i, int tiles_x, int tiles_y, int* r) {
    if (radii[2 * i] <= 0 || radii[2 * i + 1] <= 0) {
        r[0] = r[1] = r[2] = r[3] = 0;
        return;
    }
    const scalar_t cx = means2d[2 * i] / scalar_t(kTile), cy = means2d[2 * i + 1] / scalar_t(kTile);
    const scalar_t rx = scalar_t(radii[2 * i]) / scalar_t(kTile), ry = scalar_t(radii[2 * i + 1]) / scalar_t(kTile);
    auto clampi = [](double v, int hi) { return int(std::min<double>(std::max<double>(v, 0.0), hi)); };
    r[0] = clampi(std::floor(cx - rx), tiles_x);
    r[1] = clampi(std::floor(cy - ry), tiles_y);
    r[2] = clampi(std::ceil(cx + rx), tiles_x);
    r[3] = clampi(std::ceil(cy + ry), tiles_y);
}

// Counts pairs per tile into the prefix sums tile_offsets [tiles + 1]; returns the number of pairs P.
template <typename scalar_t>
int64_t bin_count(const scalar_t* means2d, const int32_t* radii, int64_t N, int W, int H, int64_t* tile_offsets) {
    const int tx_n = tiles_along(W), ty_n = tiles_along(H);
    const int64_t n_tiles = int64_t(tx_n) * ty_n;
    std::fill(tile_offsets, tile_offsets + n_tiles + 1, 0);
    for (int64_t i = 0; i < N; ++i) {
        int r[4];
        tile_rect(means2d, radii, i, tx_n, ty_n, r);
        for (int ty = r[1]; ty < r[3]; ++ty)
            for (int tx = r[0]; tx < r[2]; ++tx) tile_offsets[int64_t(ty) * tx_n + tx + 1]++;
    }
    for (int64_t t = 0; t < n_tiles; ++t) tile_offsets[t + 1] += tile_offsets[t];
    return tile_offsets[n_tiles];
}

// Fills the tile lists in surfel order, then sorts every list by (centre depth, index) in parallel: the order of a
// stable sort by depth, as gsplat's. The sort keys carry the depth (no indirection while sorting).
template <typename scalar_t>
void bin_fill(const scalar_t* means2d, const int32_t* radii, const scalar_t* depths, int64_t N, int W, int H,
              int threads, const int64_t* tile_offsets, int32_t* pair_surfel) {
    struct Key {
        scalar_t depth;
        int32_t index;
        bool operator<(const Key& o) const { return depth < o.depth || (depth == o.depth && index < o.index); }
    };
    const int tx_n = tiles_along(W), ty_n = tiles_along(H);
    const int64_t n_tiles = int64_t(tx_n) * ty_n;
    std::vector<Key> keys(tile_offsets[n_tiles]);
    std::vector<int64_t> cursor(tile_offsets, tile_offsets + n_tiles);
    for (int64_t i = 0; i < N; ++i) {
        int r[4];
        tile_rect(means2d, radii, i, tx_n, ty_n, r);
        const Key key{depths[i], int32_t(i)};
        for (int ty = r[1]; ty < r[3]; ++ty)
            for (int tx = r[0]; tx < r[2]; ++tx) keys[cursor[int64_t(ty) * tx_n + tx]++] = key;
    }
    run_workers(threads, n_tiles, 4, [&](Ranges& ranges) {
        for (int64_t lo, hi; ranges.claim(lo, hi);)
            for (int64_t t = lo; t < hi; ++t) {
                std::sort(keys.begin() + tile_offsets[t], keys.begin() + tile_offsets[t + 1]);
                for (int64_t k = tile_offsets[t]; k < tile_offsets[t + 1]; ++k) pair_surfel[k] = keys[k].index;
            }
    });
}

// surfel -> its pair positions, in ascending position order.
void build_surfel_index(const int32_t* pair_surfel, int64_t P, int64_t N, int64_t* surfel_offsets,
                        int64_t* surfel_pairs) {
    std::fill(surfel_offsets, surfel_offsets + N + 1, 0);
    for (int64_t k = 0; k < P; ++k) surfel_offsets[pair_surfel[k] + 1]++;
    for (int64_t i = 0; i < N; ++i) surfel_offsets[i + 1] += surfel_offsets[i];
    std::vector<int64_t> cursor(surfel_offsets, surfel_offsets + N);
    for (int64_t k = 0; k < P; ++k) surfel_pairs[cursor[pair_surfel[k]]++] = k;
}

template <typename scalar_t>
void reach_rects(const scalar_t* rays, const scalar_t* means2d, const scalar_t* opac, int64_t M, int W, int H,
                 int threads, int32_t* rects) {
    run_workers(threads, M, 1024, [&](Ranges& ranges) {
        for (int64_t lo, hi; ranges.claim(lo, hi);)
            for (int64_t i = lo; i < hi; ++i) {
                double T[9];
                for (int j = 0; j < 9; ++j) T[j] = rays[9 * i + j];
                reach_rect(T, double(means2d[2 * i]), double(means2d[2 * i + 1]), double(opac[i]), W, H, rects + 4 * i);
            }
    });
}

// ---------------------------------------------------------------------------------------------------------------
// Compositing

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
    scalar_t p[3], inv_p2, u, v, rho3, dx, dy, rho2, G, alpha;
    bool use3d;
};

// The pixels [xs, xe) x [ys, ye) of a surfel's reach rectangle (x0, y0, x1, y1) inside one tile.
struct PixelSpan {
    int xs, xe, ys, ye;
    bool clip(const int32_t* rect, int x0, int y0, int tw, int th) {
        ys = std::max(rect[1], y0);
        ye = std::min(rect[3], y0 + th);
        xs = std::max(rect[0], x0);
        xe = std::min(rect[2], x0 + tw);
        return ys < ye && xs < xe;
    }
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
    h.inv_p2 = scalar_t(1) / h.p[2];
    h.u = h.p[0] * h.inv_p2;
    h.v = h.p[1] * h.inv_p2;
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
    run_workers(threads, n_tiles, 1, [&](Ranges& ranges) {
        std::vector<scalar_t> T(kTilePixels), acc(kTilePixels * F);
        std::vector<int32_t> count(kTilePixels);
        std::vector<char> done(kTilePixels);
        for (int64_t lo, hi; ranges.claim(lo, hi);)
            for (int64_t t = lo; t < hi; ++t) {
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
                    PixelSpan span;
                    if (!span.clip(rects + 4 * g, x0, y0, tw, th)) continue;
                    const int ys = span.ys, ye = span.ye, xs = span.xs, xe = span.xe;
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
    });
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
    run_workers(threads, n_tiles, 1, [&](Ranges& ranges) {
        // transmittance bookkeeping in double: T is recovered by repeated division, S by a long sum
        std::vector<double> T(kTilePixels), S(kTilePixels), Tf(kTilePixels), gA(kTilePixels);
        std::vector<scalar_t> gf(kTilePixels * F);
        std::vector<int32_t> count(kTilePixels);
        std::vector<double> acc(stride);
        for (int64_t lo, hi; ranges.claim(lo, hi);)
            for (int64_t t = lo; t < hi; ++t) {
                const int x0 = int(t % b.tiles_x) * kTile, y0 = int(t / b.tiles_x) * kTile;
                const int tw = std::min(kTile, W - x0), th = std::min(kTile, H - y0);
                const int64_t start = b.tile_offsets[t], end = b.tile_offsets[t + 1];
                std::memset(pair_grads + start * stride, 0, sizeof(scalar_t) * size_t((end - start) * stride));
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
                for (int64_t k = start + max_count - 1; k >= start; --k) {
                    const int64_t g = b.pair_surfel[k];
                    PixelSpan span;
                    if (!span.clip(rects + 4 * g, x0, y0, tw, th)) continue;
                    const int ys = span.ys, ye = span.ye, xs = span.xs, xe = span.xe;
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
                            const double keep = 1.0 - double(h.alpha), inv_keep = 1.0 / keep;
                            const double T_i = T[l] * inv_keep;
                            const double w = double(h.alpha) * T_i;
                            const scalar_t* gl = &gf[l * F];
                            double fdot = 0;
                            for (int c = 0; c < F; ++c) {
                                fdot += double(gl[c]) * double(f[c]);
                                acc[kPairFixed + c] += w * double(gl[c]);
                            }
                            const scalar_t d_alpha = scalar_t(T_i * fdot - (S[l] - gA[l] * Tf[l]) * inv_keep);
                            S[l] += w * fdot;
                            T[l] = T_i;
                            if (s.o * h.G > scalar_t(0.999)) continue;  // clamped alpha: no gradient (as in gsplat)
                            acc[11] += double(d_alpha * h.G);
                            const scalar_t d_rho = scalar_t(-0.5) * h.G * s.o * d_alpha;
                            if (h.use3d) {
                                const scalar_t inv = h.inv_p2;
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
    });
}

// Sum every surfel's pair gradients (parallel over surfels, fixed order: deterministic).
template <typename scalar_t>
void reduce_pairs(const Binning& b, const scalar_t* pair_grads, int F, int64_t M, int threads, scalar_t* d_planes,
                  scalar_t* d_means2d, scalar_t* d_opac, scalar_t* d_feats) {
    const int stride = kPairFixed + F;
    run_workers(threads, M, 1024, [&](Ranges& ranges) {
        std::vector<double> sum(stride);
        for (int64_t lo, hi; ranges.claim(lo, hi);)
            for (int64_t i = lo; i < hi; ++i) {
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
    });
}

// ---------------------------------------------------------------------------------------------------------------
// Finishing (the fused path's last step, so that rendering runs no torch ops): from the composited channels
// [colour, depth, camera normal] and T_final to rgb = colour + (1 - alpha) bg, alpha = 1 - T_final,
// depth = sum w z / max(alpha, 1e-10), normals = R_cw^T (sum w n) (world frame), per pixel.

constexpr int64_t kFinishBlock = 4096;  // pixels per work item; also the fixed blocks of the reductions
constexpr double kAlphaFloor = 1e-10;

template <typename scalar_t>
void finish(int64_t n_pix, const scalar_t* feats, const scalar_t* T_final, const scalar_t* bg, const scalar_t* viewmat,
            int threads, scalar_t* rgb, scalar_t* depth, scalar_t* alpha, scalar_t* normals) {
    constexpr int F = kProjectedFeatures;
    run_workers(threads, n_pix, kFinishBlock, [&](Ranges& ranges) {
        for (int64_t lo, hi; ranges.claim(lo, hi);)
            for (int64_t p = lo; p < hi; ++p) {
                const scalar_t* f = feats + F * p;
                const scalar_t a = scalar_t(1) - T_final[p];
                const scalar_t keep = scalar_t(1) - a;
                for (int c = 0; c < 3; ++c) rgb[3 * p + c] = f[c] + keep * bg[c];
                depth[p] = f[3] / std::max(a, scalar_t(kAlphaFloor));
                alpha[p] = a;
                for (int j = 0; j < 3; ++j)
                    normals[3 * p + j] = f[4] * viewmat[j] + f[5] * viewmat[4 + j] + f[6] * viewmat[8 + j];
            }
    });
}

// Backward of `finish`: gradients of the composited channels and of alpha, and (summed over pixels in fixed blocks)
// of the background and R_cw. A null output gradient counts as zero.
template <typename scalar_t>
void finish_backward(int64_t n_pix, const scalar_t* feats, const scalar_t* T_final, const scalar_t* bg,
                     const scalar_t* viewmat, const scalar_t* g_rgb, const scalar_t* g_depth, const scalar_t* g_alpha,
                     const scalar_t* g_normals, int threads, scalar_t* g_feats, scalar_t* g_alpha_total,
                     scalar_t* d_bg, scalar_t* d_R) {
    constexpr int F = kProjectedFeatures;
    const int64_t n_blocks = (n_pix + kFinishBlock - 1) / kFinishBlock;
    std::vector<double> partial(size_t(n_blocks) * 12, 0.0);  // per block: d bg (3), d R_cw (9)
    run_workers(threads, n_pix, kFinishBlock, [&](Ranges& ranges) {
        for (int64_t lo, hi; ranges.claim(lo, hi);) {
            double* sums = &partial[size_t(lo / kFinishBlock) * 12];
            for (int64_t p = lo; p < hi; ++p) {
                const scalar_t* f = feats + F * p;
                scalar_t* gf = g_feats + F * p;
                const scalar_t a = scalar_t(1) - T_final[p];
                const scalar_t keep = scalar_t(1) - a;
                scalar_t ga = g_alpha ? g_alpha[p] : scalar_t(0);
                for (int c = 0; c < 3; ++c) {
                    const scalar_t g = g_rgb ? g_rgb[3 * p + c] : scalar_t(0);
                    gf[c] = g;
                    ga -= g * bg[c];
                    sums[c] += double(g) * double(keep);
                }
                const scalar_t gd = g_depth ? g_depth[p] : scalar_t(0);
                const scalar_t denom = std::max(a, scalar_t(kAlphaFloor));
                gf[3] = gd / denom;
                if (a >= scalar_t(kAlphaFloor)) ga -= gd * f[3] / (denom * denom);
                for (int i = 0; i < 3; ++i) {
                    scalar_t g = 0;
                    for (int j = 0; j < 3; ++j) {
                        const scalar_t gn = g_normals ? g_normals[3 * p + j] : scalar_t(0);
                        g += viewmat[4 * i + j] * gn;
                        sums[3 + 3 * i + j] += double(f[4 + i]) * double(gn);
                    }
                    gf[4 + i] = g;
                }
                g_alpha_total[p] = ga;
            }
        }
    });
    double total[12] = {0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0};
    for (int64_t b = 0; b < n_blocks; ++b)
        for (int j = 0; j < 12; ++j) total[j] += partial[size_t(b) * 12 + j];
    for (int c = 0; c < 3; ++c) d_bg[c] = scalar_t(total[c]);
    for (int j = 0; j < 9; ++j) d_R[j] = scalar_t(total[3 + j]);
}

}  // namespace

extern "C" int raster_projected_features() {
    return kProjectedFeatures;
}

extern "C" void raster_build_surfel_index(const int32_t* pair_surfel, int64_t P, int64_t N, int64_t* surfel_offsets,
                                          int64_t* surfel_pairs) {
    build_surfel_index(pair_surfel, P, N, surfel_offsets, surfel_pairs);
}

#define RASTER_CPU_API(SUFFIX, T)                                                                                      \
    extern "C" void raster_finish_##SUFFIX(int64_t n_pix, const T* feats, const T* T_final, const T* bg,             \
                                           const T* viewmat, int threads, T* rgb, T* depth, T* alpha, T* normals) {  \
        finish(n_pix, feats, T_final, bg, viewmat, threads, rgb, depth, alpha, normals);                               \
    }                                                                                                                  \
    extern "C" void raster_finish_backward_##SUFFIX(                                                                   \
        int64_t n_pix, const T* feats, const T* T_final, const T* bg, const T* viewmat, const T* g_rgb,               \
        const T* g_depth, const T* g_alpha, const T* g_normals, int threads, T* g_feats, T* g_alpha_total, T* d_bg,    \
        T* d_R) {                                                                                                      \
        finish_backward(n_pix, feats, T_final, bg, viewmat, g_rgb, g_depth, g_alpha, g_normals, threads, g_feats,     \
                        g_alpha_total, d_bg, d_R);                                                                     \
    }                                                                                                                  \
    extern "C" void raster_project_##SUFFIX(int64_t N, const T* means, const T* quats, const T* scales, const T* opac, \
                                            const T* colors, const T* viewmat, const T* K, int W, int H, int threads,  \
                                            T* rays, T* planes, T* means2d, T* depths, T* feats, int32_t* radii,       \
                                            int32_t* rects) {                                                          \
        project(N, means, quats, scales, opac, colors, viewmat, K, W, H, threads, rays, planes, means2d, depths,       \
                feats, radii, rects);                                                                                  \
    }                                                                                                                  \
    extern "C" void raster_project_backward_##SUFFIX(                                                                  \
        int64_t N, const T* means, const T* quats, const T* scales, const T* viewmat, const T* K,                      \
        const int32_t* radii, const T* d_planes, const T* d_means2d, const T* d_feats, int threads, T* d_means,        \
        T* d_quats, T* d_scales, T* d_colors, T* d_viewmat) {                                                          \
        project_backward(N, means, quats, scales, viewmat, K, radii, d_planes, d_means2d, d_feats, threads, d_means,   \
                         d_quats, d_scales, d_colors, d_viewmat);                                                      \
    }                                                                                                                  \
    extern "C" int64_t raster_bin_count_##SUFFIX(const T* means2d, const int32_t* radii, int64_t N, int W, int H,      \
                                                 int64_t* tile_offsets) {                                              \
        return bin_count(means2d, radii, N, W, H, tile_offsets);                                                       \
    }                                                                                                                  \
    extern "C" void raster_bin_fill_##SUFFIX(const T* means2d, const int32_t* radii, const T* depths, int64_t N,       \
                                             int W, int H, int threads, const int64_t* tile_offsets,                   \
                                             int32_t* pair_surfel) {                                                   \
        bin_fill(means2d, radii, depths, N, W, H, threads, tile_offsets, pair_surfel);                                 \
    }                                                                                                                  \
    extern "C" void raster_reach_rects_##SUFFIX(const T* rays, const T* means2d, const T* opac, int64_t M, int W,      \
                                                int H, int threads, int32_t* rects) {                                  \
        reach_rects(rays, means2d, opac, M, W, H, threads, rects);                                                     \
    }                                                                                                                  \
    extern "C" void raster_forward_##SUFFIX(const int64_t* tile_offsets, const int32_t* pair_surfel,                   \
                                            const int32_t* rects, const T* planes, const T* means2d, const T* opac,    \
                                            const T* feats, int F, int W, int H, int threads, T* out_feat, T* out_T,   \
                                            int32_t* out_count) {                                                      \
        const Binning b{tiles_along(W), tiles_along(H), tile_offsets, pair_surfel, nullptr, nullptr};                  \
        forward_impl(b, rects, planes, means2d, opac, feats, F, W, H, threads, out_feat, out_T, out_count);            \
    }                                                                                                                  \
    extern "C" void raster_backward_##SUFFIX(                                                                          \
        const int64_t* tile_offsets, const int32_t* pair_surfel, const int64_t* surfel_offsets,                        \
        const int64_t* surfel_pairs, const int32_t* rects, const T* planes, const T* means2d, const T* opac,           \
        const T* feats, int64_t M, int F, int W, int H, int threads, const T* T_final, const int32_t* counts,          \
        const T* g_feat, const T* g_alpha, T* pair_grads, T* d_planes, T* d_means2d, T* d_opac, T* d_feats) {          \
        const Binning b{tiles_along(W), tiles_along(H), tile_offsets, pair_surfel, surfel_offsets, surfel_pairs};      \
        backward_impl(b, rects, planes, means2d, opac, feats, F, W, H, threads, T_final, counts, g_feat, g_alpha,      \
                      pair_grads);                                                                                     \
        reduce_pairs(b, pair_grads, F, M, threads, d_planes, d_means2d, d_opac, d_feats);                              \
    }

RASTER_CPU_API(f32, float)
RASTER_CPU_API(f64, double)
