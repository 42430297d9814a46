// Plane-sweep multi-view stereo kernels: the ZNCC cost volume, the fusion of the views' costs, semi-global
// aggregation. Plain C ABI (no torch headers); worker/depth/mvs_cpu.py owns every buffer and calls these through
// ctypes. worker/depth/reference.py is the numpy twin of each function (the test oracle).
//
// Conventions: images are row-major float32 [H, W] grey levels; pixel (row i, col j) has its centre at
// (j + 0.5, i + 0.5). Hypothesis d is the fronto-parallel plane at inverse depth w_d of the reference camera; the
// reference pixel p lands in view n at the homogeneous point A_n p + w_d b_n (A_n = K R_nr K^-1, b_n = K t_nr).
// Costs are 1 - ZNCC over a (2r+1)^2 window clipped at the image border, in [0, 2]; kUnseen (< 0) where the
// centre's sample falls outside view n or behind it. Neighbour samples are bilinear with clamped coordinates.

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <thread>
#include <vector>

namespace {

constexpr float kUnseen = -1.0f;
constexpr double kMinZ = 1e-9;

// Workers used for n jobs on `threads` threads.
inline int worker_count(int threads, int64_t n) {
    return int(std::max<int64_t>(1, std::min<int64_t>(threads, n)));
}

// Calls job(i, worker) for i in [0, n), one index at a time, on worker_count(threads, n) workers (the caller is
// worker 0, the others are std::threads; idle workers wait in join, they do not spin).
template <typename Job>
void parallel_jobs(int threads, int64_t n, Job job) {
    std::atomic<int64_t> next{0};
    auto drain = [&](int worker) {
        for (int64_t i = next.fetch_add(1); i < n; i = next.fetch_add(1)) job(i, worker);
    };
    std::vector<std::thread> pool;
    for (int w = 1; w < worker_count(threads, n); ++w) pool.emplace_back(drain, w);
    drain(0);
    for (std::thread& t : pool) t.join();
}

// h[x] = sum of c[x .. x + 2R] (c is zero-padded by R on each side): the window sums along a row. R is a
// template parameter so that the inner sum unrolls and the loop over x vectorises.
template <int R>
void box_sums_fixed(const float* c, float* h, int W) {
    for (int x = 0; x < W; ++x) {
        float sum = 0.0f;
        for (int j = 0; j <= 2 * R; ++j) sum += c[x + j];
        h[x] = sum;
    }
}

void box_sums(const float* c, float* h, int W, int r) {
    switch (r) {
        case 1: return box_sums_fixed<1>(c, h, W);
        case 2: return box_sums_fixed<2>(c, h, W);
        case 3: return box_sums_fixed<3>(c, h, W);
        case 4: return box_sums_fixed<4>(c, h, W);
        case 5: return box_sums_fixed<5>(c, h, W);
        case 6: return box_sums_fixed<6>(c, h, W);
        default: return box_sums_fixed<7>(c, h, W);
    }
}

// One (view, hypothesis) plane of the cost volume. Each row of warped samples w, w^2 and ref * w enters running
// column sums when the window reaches it and leaves when the window has passed; summing 2r + 1 neighbouring column
// sums (zero-padded at the sides) then gives the window sums. The loops over a row vectorise except the gather.
struct PlaneSweep {
    int H, W, r;
    float min_var;
    const float* ref;
    const float* ref_sum;  // [H, W] window sums of the reference
    const float* ref_ssd;  // [H, W] window sums of squared deviations from the window mean
    std::vector<float> ring;       // (2r + 2) rows x 3 quantities x W
    std::vector<float> col;        // 3 quantities x (W + 2r): column sums, r zeros on each side
    std::vector<float> u, v, box;  // [W] bilinear weights within each sample's cell; 3 x W window sums of a row
    std::vector<float> cell;       // [W] index of each sample's top-left pixel (a whole number)
    std::vector<float> cols;       // [W] columns inside each window
    std::vector<float> seen;       // (2r + 2) rows x W: 1 where the centre sample is inside the view, else 0

    PlaneSweep(int H_, int W_, int r_, float min_var_, const float* ref_, const float* ref_sum_, const float* ref_ssd_)
        : H(H_), W(W_), r(r_), min_var(min_var_), ref(ref_), ref_sum(ref_sum_), ref_ssd(ref_ssd_),
          ring(size_t(2 * r_ + 2) * 3 * W_), col(size_t(3) * (W_ + 2 * r_)), u(W_), v(W_), box(size_t(3) * W_),
          cell(W_), cols(W_), seen(size_t(2 * r_ + 2) * W_) {
        for (int x = 0; x < W; ++x) cols[x] = float(std::min(W - 1, x + r) - std::max(0, x - r) + 1);
    }

    void warp_row(const float* src, const double* A, const double* b, double w, int y) {
        const int slot = y % (2 * r + 2);
        float* q = ring.data() + size_t(slot) * 3 * W;
        float* s = seen.data() + size_t(slot) * W;
        const float* ref_row = ref + int64_t(y) * W;
        const double py = y + 0.5;
        const float ax = float(A[0]), ay = float(A[3]), az = float(A[6]);
        const float hx0 = float(A[1] * py + A[2] + w * b[0]) + 0.5f * ax;
        const float hy0 = float(A[4] * py + A[5] + w * b[1]) + 0.5f * ay;
        const float hz0 = float(A[7] * py + A[8] + w * b[2]) + 0.5f * az;
        const float umax = float(W - 1), vmax = float(H - 1);
        const float xmax = float(W - 2), ymax = float(H - 2), width = float(W);
        for (int x = 0; x < W; ++x) {  // sample positions, bilinear cells and weights (vectorises)
            const float hz = az * float(x) + hz0;
            const bool front = hz > float(kMinZ);
            const float inv = 1.0f / (front ? hz : 1.0f);
            const float ux = front ? (ax * float(x) + hx0) * inv - 0.5f : 0.0f;
            const float vy = front ? (ay * float(x) + hy0) * inv - 0.5f : 0.0f;
            s[x] = (front && ux >= 0.0f && ux <= umax && vy >= 0.0f && vy <= vmax) ? 1.0f : 0.0f;
            const float uc = std::min(std::max(ux, 0.0f), umax), vc = std::min(std::max(vy, 0.0f), vmax);
            const float x0 = std::min(float(int(uc)), xmax), y0 = std::min(float(int(vc)), ymax);
            u[x] = uc - x0;
            v[x] = vc - y0;
            cell[x] = y0 * width + x0;  // exact in float for images below 2^24 pixels
        }
        for (int x = 0; x < W; ++x) {  // the gather
            const float* r0 = src + int(cell[x]);
            const float* r1 = r0 + W;
            const float top = r0[0] + u[x] * (r0[1] - r0[0]);
            const float bottom = r1[0] + u[x] * (r1[1] - r1[0]);
            q[x] = top + v[x] * (bottom - top);
        }
        for (int x = 0; x < W; ++x) {
            q[W + x] = q[x] * q[x];
            q[2 * W + x] = ref_row[x] * q[x];
        }
    }

    // Column sums += row `enter` - row `leave` (either may be -1: none), in one pass over the sums.
    void update_columns(int enter, int leave) {
        const size_t slots = size_t(2 * r + 2);
        const float* qa = enter >= 0 ? ring.data() + size_t(enter) % slots * 3 * W : nullptr;
        const float* qs = leave >= 0 ? ring.data() + size_t(leave) % slots * 3 * W : nullptr;
        const int stride = W + 2 * r;
        for (int k = 0; k < 3; ++k) {
            float* c = col.data() + size_t(k) * stride + r;
            const float* a = qa ? qa + size_t(k) * W : nullptr;
            const float* b = qs ? qs + size_t(k) * W : nullptr;
            if (a && b) {
                for (int x = 0; x < W; ++x) c[x] += a[x] - b[x];
            } else if (a) {
                for (int x = 0; x < W; ++x) c[x] += a[x];
            } else if (b) {
                for (int x = 0; x < W; ++x) c[x] -= b[x];
            }
        }
    }

    void run(const float* src, const double* A, const double* b, double w, float* out) {
        std::fill(col.begin(), col.end(), 0.0f);
        for (int y = 0; y < std::min(r, H); ++y) {
            warp_row(src, A, b, w, y);
            update_columns(y, -1);
        }
        for (int y = 0; y < H; ++y) {
            const int enter = y + r < H ? y + r : -1, leave = y - r - 1;
            if (enter >= 0) warp_row(src, A, b, w, enter);
            update_columns(enter, leave);
            const int rows = std::min(H - 1, y + r) - std::max(0, y - r) + 1;
            finish_row(y, rows, out + int64_t(y) * W);
        }
    }

    void finish_row(int y, int rows, float* out) {
        const int stride = W + 2 * r;
        for (int k = 0; k < 3; ++k) box_sums(col.data() + size_t(k) * stride, box.data() + size_t(k) * W, W, r);
        const float *s1 = box.data(), *s2 = s1 + W, *s3 = s2 + W;
        const float* s = seen.data() + size_t(y % (2 * r + 2)) * W;
        const float* rs = ref_sum + int64_t(y) * W;
        const float* rv = ref_ssd + int64_t(y) * W;
        for (int x = 0; x < W; ++x) {  // branch-free so that it vectorises
            const float n = float(rows) * cols[x], inv_n = 1.0f / n;
            const float var_w = s2[x] - s1[x] * s1[x] * inv_n;
            const float cov = s3[x] - rs[x] * s1[x] * inv_n;
            const float textured = (var_w > n * min_var && rv[x] > n * min_var) ? 1.0f : 0.0f;  // else ZNCC 0
            const float zncc = textured * cov / std::sqrt(std::max(var_w * rv[x], 1e-30f));
            const float cost = 1.0f - std::min(1.0f, std::max(-1.0f, zncc));
            out[x] = s[x] * cost + (1.0f - s[x]) * kUnseen;
        }
    }
};

// Semi-global aggregation along one direction (dx, dy), accumulated into `total` [P, D].
void sgm_path(int H, int W, int D, const float* cost, float P1, float P2, int dx, int dy, float* total) {
    std::vector<float> prev_row(size_t(W) * D), cur_row(size_t(W) * D), prev_min(W), cur_min(W);
    for (int yi = 0; yi < H; ++yi) {
        const int y = dy >= 0 ? yi : H - 1 - yi;
        for (int xi = 0; xi < W; ++xi) {
            const int x = dx >= 0 ? xi : W - 1 - xi;
            const int px = x - dx;
            const bool has_prev = px >= 0 && px < W && (dy == 0 || yi > 0);
            const float* c = cost + (int64_t(y) * W + x) * D;
            float* L = cur_row.data() + size_t(x) * D;
            float* t = total + (int64_t(y) * W + x) * D;
            float best = c[0];
            if (!has_prev) {
                for (int d = 0; d < D; ++d) {
                    L[d] = c[d];
                    t[d] += c[d];
                    best = std::min(best, c[d]);
                }
            } else {
                const float* Lp = (dy == 0 ? cur_row.data() : prev_row.data()) + size_t(px) * D;
                const float m = dy == 0 ? cur_min[px] : prev_min[px];
                const float jump = m + P2;
                // ends first so that the loop over the interior has no branches (and vectorises)
                L[0] = c[0] + std::min(std::min(Lp[0], jump), Lp[1] + P1) - m;
                L[D - 1] = c[D - 1] + std::min(std::min(Lp[D - 1], jump), Lp[D - 2] + P1) - m;
                best = std::min(L[0], L[D - 1]);
                t[0] += L[0];
                t[D - 1] += L[D - 1];
                for (int d = 1; d < D - 1; ++d) {
                    const float v = std::min(std::min(Lp[d], jump), std::min(Lp[d - 1], Lp[d + 1]) + P1);
                    L[d] = c[d] + v - m;
                    t[d] += L[d];
                    best = std::min(best, L[d]);
                }
            }
            cur_min[x] = best;
        }
        std::swap(prev_row, cur_row);
        std::swap(prev_min, cur_min);
    }
}

}  // namespace

extern "C" void mvs_cost_volume(int H, int W, int N, int D, const float* ref, const float* ref_sum,
                                const float* ref_ssd, const float* views, const double* A, const double* b,
                                const double* inv_depths, int radius, float min_var, int threads, float* cost) {
    const int64_t P = int64_t(H) * W;
    std::vector<PlaneSweep> sweeps;  // one set of row buffers per worker
    for (int t = 0; t < worker_count(threads, int64_t(N) * D); ++t)
        sweeps.emplace_back(H, W, radius, min_var, ref, ref_sum, ref_ssd);
    parallel_jobs(threads, int64_t(N) * D, [&](int64_t job, int worker) {
        const int n = int(job / D), d = int(job % D);
        sweeps[size_t(worker)].run(views + n * P, A + 9 * n, b + 3 * n, inv_depths[d], cost + job * P);
    });
}

// fused[p, d] = mean of the `keep` lowest seen costs of the N views (1 where no view sees p at d);
// view_min[n, p] = the lowest seen cost of view n over all hypotheses (kUnseen if it never sees p).
// Per block of pixels, a compare-exchange network keeps each pixel's `keep` lowest costs sorted; every loop over
// the block is branch-free (vectorises), and the block's [pixels, D] result is copied out in one piece.
extern "C" void mvs_fuse_views(int N, int D, int64_t P, const float* cost, int keep, int threads, float* fused,
                               float* view_min) {
    constexpr int kBlock = 64;
    constexpr float kBig = 1e9f;  // an unseen cost: sorts after every seen one
    parallel_jobs(threads, (P + kBlock - 1) / kBlock, [&](int64_t block, int) {
        const int64_t p0 = block * kBlock;
        const int len = int(std::min<int64_t>(P - p0, kBlock));
        std::vector<float> low(size_t(keep) * kBlock), mins(size_t(N) * kBlock, kBig), count(kBlock), value(kBlock);
        std::vector<float> out(size_t(kBlock) * D);
        for (int d = 0; d < D; ++d) {
            std::fill(low.begin(), low.end(), kBig);
            std::fill(count.begin(), count.end(), 0.0f);
            for (int n = 0; n < N; ++n) {
                const float* c = cost + (int64_t(n) * D + d) * P + p0;
                float* m = mins.data() + size_t(n) * kBlock;
                for (int i = 0; i < len; ++i) {
                    const float seen = c[i] >= 0.0f ? 1.0f : 0.0f;
                    value[i] = c[i] >= 0.0f ? c[i] : kBig;
                    count[i] += seen;
                    m[i] = std::min(m[i], value[i]);
                }
                for (int k = 0; k < keep; ++k) {
                    float* slot = low.data() + size_t(k) * kBlock;
                    for (int i = 0; i < len; ++i) {
                        const float lo = std::min(slot[i], value[i]);
                        value[i] = std::max(slot[i], value[i]);
                        slot[i] = lo;
                    }
                }
            }
            for (int i = 0; i < len; ++i) {
                const float used = std::min(float(keep), count[i]);
                float sum = 0.0f;
                for (int k = 0; k < keep; ++k) sum += float(k) < used ? low[size_t(k) * kBlock + i] : 0.0f;
                out[size_t(i) * D + d] = used > 0.0f ? sum / used : 1.0f;
            }
        }
        std::copy(out.begin(), out.begin() + size_t(len) * D, fused + p0 * D);
        for (int n = 0; n < N; ++n)
            for (int i = 0; i < len; ++i) {
                const float m = mins[size_t(n) * kBlock + i];
                view_min[n * P + p0 + i] = m < kBig ? m : kUnseen;
            }
    });
}

// total [P, D] = sum over `paths` (4: horizontal and vertical; 8: also the diagonals) of the SGM path costs.
// With several threads, each thread sums its paths into its own buffer (scratch: (threads - 1) x P x D floats).
extern "C" void mvs_sgm(int H, int W, int D, const float* cost, float P1, float P2, int paths, int threads,
                        float* total, float* scratch) {
    static const int kDirs[8][2] = {{1, 0}, {-1, 0}, {0, 1}, {0, -1}, {1, 1}, {-1, 1}, {1, -1}, {-1, -1}};
    const int64_t size = int64_t(H) * W * D;
    const int workers = worker_count(threads, paths);
    std::fill(total, total + size, 0.0f);
    std::fill(scratch, scratch + size * (workers - 1), 0.0f);
    parallel_jobs(threads, paths, [&](int64_t k, int worker) {
        float* out = worker == 0 ? total : scratch + size * (worker - 1);
        sgm_path(H, W, D, cost, P1, P2, kDirs[k][0], kDirs[k][1], out);
    });
    for (int t = 1; t < workers; ++t) {
        const float* s = scratch + size * (t - 1);
        parallel_jobs(threads, H, [&](int64_t y, int) {
            for (int64_t i = y * W * D; i < (y + 1) * W * D; ++i) total[i] += s[i];
        });
    }
}

// Per pixel, from the aggregated costs total [P, D] and the fused matching costs fused [P, D]:
//   index [P]: the best hypothesis of total, refined by a parabola through the fused costs around it;
//   interior [P]: the best is not at either end of the range;
//   uniq [P]: 1 - best / runner-up of total more than one hypothesis away, in [0, 1];
//   match_margin [P]: how far the best's fused cost lies below every hypothesis more than two away (ramps and flat
//     shading match equally well at many depths);
//   photo [P]: 1 - fused cost at the best, clipped to [0, 1];
//   support [P]: views that see the point near the best (+-1) with a cost within `margin` of their own lowest and
//     at most max_cost.
extern "C" void mvs_decide_terms(int N, int D, int64_t P, const float* total, const float* fused, const float* cost,
                                 const float* view_min, float margin, float max_cost, int threads, double* index,
                                 uint8_t* interior, float* uniq, float* match_margin, float* photo,
                                 int16_t* support) {
    constexpr int64_t kBlock = 256;
    parallel_jobs(threads, (P + kBlock - 1) / kBlock, [&](int64_t block, int) {
        for (int64_t p = block * kBlock; p < std::min(P, (block + 1) * kBlock); ++p) {
            const float* t = total + p * D;
            int best = 0;
            for (int d = 1; d < D; ++d)
                if (t[d] < t[best]) best = d;
            const bool inside = best > 0 && best < D - 1;
            double delta = 0.0;
            if (inside) {  // on the matching cost: SGM's penalties would pull the fit towards whole hypotheses
                const float* f = fused + p * D;
                const double a = f[best - 1], b = f[best], c = f[best + 1], curvature = a - 2.0 * b + c;
                if (curvature > 0) delta = std::min(0.5, std::max(-0.5, 0.5 * (a - c) / curvature));
            }
            index[p] = best + delta;
            interior[p] = inside;
            float runner_up = -1.0f;
            for (int d = 0; d < D; ++d)
                if (std::abs(d - best) > 1 && (runner_up < 0.0f || t[d] < runner_up)) runner_up = t[d];
            const double ratio = runner_up > 0.0f ? double(t[best]) / runner_up : 1.0;
            uniq[p] = float(std::min(1.0, std::max(0.0, 1.0 - ratio)));
            const float* f = fused + p * D;
            float rival = 2.0f;  // the matching cost cannot exceed 2
            for (int d = 0; d < D; ++d)
                if (std::abs(d - best) > 2) rival = std::min(rival, f[d]);
            match_margin[p] = std::max(0.0f, rival - f[best]);
            photo[p] = std::min(1.0f, std::max(0.0f, 1.0f - f[best]));
            int16_t agree = 0;
            for (int n = 0; n < N; ++n) {
                float near = -1.0f;
                for (int step = -1; step <= 1; ++step) {
                    const int d = std::min(D - 1, std::max(0, best + step));
                    const float c = cost[(int64_t(n) * D + d) * P + p];
                    if (c >= 0.0f && (near < 0.0f || c < near)) near = c;
                }
                agree += near >= 0.0f && near <= view_min[n * P + p] + margin && near <= max_cost;
            }
            support[p] = agree;
        }
    });
}
