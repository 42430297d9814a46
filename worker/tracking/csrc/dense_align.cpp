// Dense RGB-D alignment kernels: one pyramid level's points and normals, the depth downsampling between levels,
// and the Gauss-Newton normal equations of the photometric and the point-to-plane terms for one iteration.
// Plain C ABI; worker/tracking/dense_native.py owns every buffer and calls these through ctypes (which releases the
// GIL). worker/tracking/dense_reference.py is the numpy twin of each function (the test oracle) and documents the
// maths; the arithmetic below follows it operation by operation (float32 where it works in float32).
//
// Conventions: images row-major [h, w]; pixel (row i, col j) has its centre at (j + 0.5, i + 0.5). K is passed
// as (fx, fy, cx, cy). T is the 4x4 row-major float64 T_cur_ref. The update is a left perturbation exp(delta) T,
// delta = (omega, v), so the jacobian row of a residual a . (T p) is [p x a, a].

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <utility>
#include <vector>

namespace {

// The two middle values of `values` (equal for an odd count); np.median is their mean. Reorders `values`.
std::pair<double, double> middle_pair(std::vector<double>& values) {
    const size_t n = values.size();
    if (n == 0) return {0.0, 0.0};
    auto middle = values.begin() + n / 2;
    std::nth_element(values.begin(), middle, values.end());
    const double upper = *middle;
    return {n % 2 ? upper : *std::max_element(values.begin(), middle), upper};
}

double median(std::vector<double>& values) {
    const auto [lower, upper] = middle_pair(values);
    return values.size() % 2 ? upper : (lower + upper) / 2.0;
}

// max(1.4826 * median(|r - centre|), floor) with centre = median(r): the robust (MAD) scale of the residuals.
double robust_scale(const std::vector<double>& r, double centre, double floor, std::vector<double>& scratch) {
    if (r.empty()) return floor;
    scratch.resize(r.size());
    for (size_t i = 0; i < r.size(); ++i) scratch[i] = std::fabs(r[i] - centre);
    return std::max(1.4826 * median(scratch), floor);
}

double huber_weight(double r, double scale, double k) {
    const double a = std::fabs(r) / std::max(scale, 1e-12);
    return a <= k ? 1.0 : k / std::max(a, 1e-12);
}

// H += w J J^T and g += w J r for a jacobian row J = [p x a, a]; H is accumulated in its upper triangle.
inline void accumulate(const double p[3], const double a[3], double w, double r, double* H, double* g) {
    const double J[6] = {p[1] * a[2] - p[2] * a[1], p[2] * a[0] - p[0] * a[2], p[0] * a[1] - p[1] * a[0],
                         a[0], a[1], a[2]};
    for (int i = 0; i < 6; ++i) {
        const double wi = w * J[i];
        g[i] += wi * r;
        for (int j = i; j < 6; ++j) H[i * 6 + j] += wi * J[j];
    }
}

void symmetrize(double* H) {
    for (int i = 0; i < 6; ++i)
        for (int j = 0; j < i; ++j) H[i * 6 + j] = H[j * 6 + i];
}

inline void transform(const double* T, const double* p, double q[3]) {
    for (int k = 0; k < 3; ++k) q[k] = T[4 * k] * p[0] + T[4 * k + 1] * p[1] + T[4 * k + 2] * p[2] + T[4 * k + 3];
}

// Point p (world) moved by T into q, and the pixel (u, v) it projects to with K = (fx, fy, cx, cy).
inline void move_and_project(const double* T, const double* K, const double* p, double q[3], double& u, double& v) {
    transform(T, p, q);
    const double z = std::max(q[2], 1e-9);
    u = K[0] * q[0] / z + K[2];
    v = K[1] * q[1] / z + K[3];
}

// Bilinear sample at continuous pixel coordinates (u, v), centres at +0.5; (u, v) must lie in [0.5, w - 0.5) x
// [0.5, h - 0.5) so that the four neighbours exist.
inline double bilinear(const float* image, int w, double u, double v) {
    const double x = double(float(u - 0.5)), y = double(float(v - 0.5));  // the reference samples at float32
    const int ix = int(x), iy = int(y);
    const double fx = x - ix, fy = y - iy;
    const float* row = image + int64_t(iy) * w + ix;
    const double top = row[0] + fx * (double(row[1]) - row[0]);
    const double bottom = row[w] + fx * (double(row[w + 1]) - row[w]);
    return top + fy * (bottom - top);
}

}  // namespace

extern "C" {

// Camera-frame points [h, w, 3] (float32; z = depth, 0 where unknown) of a depth map under K = (fx, fy, cx, cy).
void dense_points(int h, int w, const float* depth, const double* K, float* points) {
    for (int i = 0; i < h; ++i) {
        const double y = (i + 0.5 - K[3]) / K[1];
        for (int j = 0; j < w; ++j) {
            const double x = (j + 0.5 - K[2]) / K[0];
            const float d = depth[int64_t(i) * w + j];
            float* p = points + (int64_t(i) * w + j) * 3;
            p[0] = float(x * d);
            p[1] = float(y * d);
            p[2] = d;
        }
    }
}

// Unit normals [h, w, 3] (float32) from central differences of the point grid, facing the camera; 0 on the
// border, at missing depth and where a neighbour's depth differs by more than edge_ratio x depth.
void dense_normals(int h, int w, const float* points, float edge_ratio, float* normals) {
    std::fill(normals, normals + int64_t(h) * w * 3, 0.0f);
    for (int i = 1; i < h - 1; ++i) {
        for (int j = 1; j < w - 1; ++j) {
            const int64_t at = int64_t(i) * w + j;
            const float* p = points + at * 3;
            const float* right = p + 3;
            const float* left = p - 3;
            const float* down = p + int64_t(w) * 3;
            const float* up = p - int64_t(w) * 3;
            const float z = p[2];
            if (!(z > 0.0f)) continue;
            const float limit = edge_ratio * z;
            bool good = true;
            for (const float* q : {right, left, down, up})
                good = good && q[2] > 0.0f && std::fabs(q[2] - z) <= limit;
            if (!good) continue;
            const float dx[3] = {right[0] - left[0], right[1] - left[1], right[2] - left[2]};
            const float dy[3] = {down[0] - up[0], down[1] - up[1], down[2] - up[2]};
            const float c[3] = {dx[1] * dy[2] - dx[2] * dy[1], dx[2] * dy[0] - dx[0] * dy[2],
                                dx[0] * dy[1] - dx[1] * dy[0]};
            const float norm = std::sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2]);
            if (!(norm > 0.0f)) continue;
            const float facing = c[0] * p[0] + c[1] * p[1] + c[2] * p[2];
            const float scale = float((facing > 0.0f ? -1.0 : 1.0) / double(std::max(norm, 1e-12f)));
            float* n = normals + at * 3;
            for (int k = 0; k < 3; ++k) n[k] = c[k] * scale;
        }
    }
}

// Depth [h / 2, w / 2] from 2x2 blocks: the mean of the valid depths, 0 where fewer than two are valid or the
// block straddles a depth edge (max - min > edge_ratio x mean).
void dense_downsample_depth(int h, int w, const float* depth, double edge_ratio, float* out) {
    const int oh = h / 2, ow = w / 2;
    for (int i = 0; i < oh; ++i) {
        for (int j = 0; j < ow; ++j) {
            const float* row = depth + int64_t(2 * i) * w + 2 * j;
            const float block[4] = {row[0], row[1], row[w], row[w + 1]};
            float sum = 0.0f, hi = -INFINITY, lo = INFINITY;
            int count = 0;
            for (float d : block) {
                sum += d;
                if (d > 0.0f) {
                    ++count;
                    hi = std::max(hi, d);
                    lo = std::min(lo, d);
                }
            }
            const double mean = count > 0 ? double(sum) / count : 0.0;
            const bool keep = count >= 2 && double(hi - lo) <= edge_ratio * mean;
            out[int64_t(i) * ow + j] = keep ? float(mean) : 0.0f;
        }
    }
}

// The photometric term of one Gauss-Newton iteration. Reference points P [n, 3] (float64) with intensities
// I [n] are moved by T and projected into the current image (grey, grad_x, grad_y: float32 [h, w]); those landing
// inside (1 pixel from the border) give r = sampled - I minus its median, robust scale s = MAD (>= floor),
// Huber weights x weight / s^2. out = [H (36), g (6), points used, scale]; points used = 0 (H, g zero) when fewer
// than min_points land inside.
void dense_photometric_system(int64_t n, const double* P, const double* I, const double* T, const double* K,
                              int h, int w, const float* grey, const float* grad_x, const float* grad_y,
                              double floor, double weight, double huber_k, int64_t min_points, double* out) {
    std::fill(out, out + 44, 0.0);
    std::vector<double> r(n), scratch, moved(5 * n);  // moved: (x, y, z, u, v) of each point landing inside
    int64_t m = 0;
    for (int64_t i = 0; i < n; ++i) {
        double p[3], u, v;
        move_and_project(T, K, P + 3 * i, p, u, v);
        if (!(p[2] > 0.0 && u >= 1.0 && u < w - 1 && v >= 1.0 && v < h - 1)) continue;
        r[m] = bilinear(grey, w, u, v) - I[i];
        double* q = moved.data() + 5 * m++;
        q[0] = p[0], q[1] = p[1], q[2] = p[2], q[3] = u, q[4] = v;
    }
    r.resize(m);
    if (m < min_points) return;
    // r -= median(r); the median of the result is then that of the shifted middle pair (no second selection)
    scratch.assign(r.begin(), r.end());
    const auto [lower, upper] = middle_pair(scratch);
    const double offset = m % 2 ? upper : (lower + upper) / 2.0;
    for (double& value : r) value -= offset;
    const double centre = m % 2 ? upper - offset : ((lower - offset) + (upper - offset)) / 2.0;
    const double scale = robust_scale(r, centre, floor, scratch);
    const double whiten = weight / (scale * scale);
    double* H = out;
    double* g = out + 36;
    for (int64_t k = 0; k < m; ++k) {
        const double* q = moved.data() + 5 * k;
        const double gx = bilinear(grad_x, w, q[3], q[4]), gy = bilinear(grad_y, w, q[3], q[4]);
        const double z = q[2];
        // d(intensity)/d(point) = grad . d(pixel)/d(point)
        const double a[3] = {gx * K[0] / z, gy * K[1] / z, -(gx * K[0] * q[0] + gy * K[1] * q[1]) / (z * z)};
        accumulate(q, a, huber_weight(r[k], scale, huber_k) * whiten, r[k], H, g);
    }
    symmetrize(H);
    out[42] = double(m);
    out[43] = scale;
}

// The point-to-plane term of one Gauss-Newton iteration. Reference points P [n, 3] moved by T are associated with
// the current frame's point and normal (float32 [h, w, 3]) at the pixel they project to; a pair counts when it
// has depth and a normal and lies closer than max_association x depth. r = (p - q) . n / z, J = [p x n, n] / z,
// robust scale s = MAD (>= floor), Huber weights x weight / s^2. out = [H (36), g (6), points used, scale,
// pairs found]; points used = 0 (H, g zero) when fewer than min_points pairs are found.
void dense_geometric_system(int64_t n, const double* P, const double* T, const double* K, int h, int w,
                            const float* points, const float* normals, double max_association, double floor,
                            double weight, double huber_k, int64_t min_points, double* out) {
    std::fill(out, out + 45, 0.0);
    std::vector<double> r(n), scratch, moved(6 * n);  // moved: (x, y, z) and the normal of each pair found
    int64_t m = 0;
    for (int64_t i = 0; i < n; ++i) {
        double p[3], u, v;
        move_and_project(T, K, P + 3 * i, p, u, v);
        if (!(p[2] > 0.0 && u >= 0.0 && u < w && v >= 0.0 && v < h)) continue;
        const int64_t at = int64_t(v) * w + int64_t(u);
        const float* q = points + 3 * at;
        const float* nq = normals + 3 * at;
        if (!(q[2] > 0.0f) || std::fabs(nq[0]) + std::fabs(nq[1]) + std::fabs(nq[2]) <= 0.0f) continue;
        const double d[3] = {p[0] - q[0], p[1] - q[1], p[2] - q[2]};
        if (!(std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) < max_association * p[2])) continue;
        r[m] = (d[0] * nq[0] + d[1] * nq[1] + d[2] * nq[2]) / p[2];
        double* s = moved.data() + 6 * m++;
        s[0] = p[0], s[1] = p[1], s[2] = p[2], s[3] = nq[0], s[4] = nq[1], s[5] = nq[2];
    }
    r.resize(m);
    out[44] = double(m);
    if (m < min_points) return;
    scratch.assign(r.begin(), r.end());
    const double scale = robust_scale(r, median(scratch), floor, scratch);
    const double whiten = weight / (scale * scale);
    double* H = out;
    double* g = out + 36;
    for (int64_t k = 0; k < m; ++k) {
        const double* q = moved.data() + 6 * k;
        const double inv_z = 1.0 / q[2];
        const double p[3] = {q[0], q[1], q[2]};
        const double a[3] = {q[3] * inv_z, q[4] * inv_z, q[5] * inv_z};  // J = [p x n, n] / z
        accumulate(p, a, huber_weight(r[k], scale, huber_k) * whiten, r[k], H, g);
    }
    symmetrize(H);
    out[42] = double(m);
    out[43] = scale;
}

// 6x6 solve by Gaussian elimination with partial pivoting (as LAPACK's dgesv); false when a pivot is exactly 0.
static bool solve6(double A[36], double b[6], double x[6]) {
    for (int c = 0; c < 6; ++c) {
        int pivot = c;
        for (int r = c + 1; r < 6; ++r)
            if (std::fabs(A[r * 6 + c]) > std::fabs(A[pivot * 6 + c])) pivot = r;
        if (A[pivot * 6 + c] == 0.0) return false;
        if (pivot != c) {
            for (int k = 0; k < 6; ++k) std::swap(A[c * 6 + k], A[pivot * 6 + k]);
            std::swap(b[c], b[pivot]);
        }
        for (int r = c + 1; r < 6; ++r) {
            const double f = A[r * 6 + c] / A[c * 6 + c];
            for (int k = c; k < 6; ++k) A[r * 6 + k] -= f * A[c * 6 + k];
            b[r] -= f * b[c];
        }
    }
    for (int r = 5; r >= 0; --r) {
        double sum = b[r];
        for (int k = r + 1; k < 6; ++k) sum -= A[r * 6 + k] * x[k];
        x[r] = sum / A[r * 6 + r];
    }
    return true;
}

// T <- exp(delta) T for delta = (omega, v) (Rodrigues' formula and the left Jacobian, as dense_alignment._se3_exp).
static void se3_left_update(const double delta[6], double* T) {
    const double* o = delta;
    const double theta = std::sqrt(o[0] * o[0] + o[1] * o[1] + o[2] * o[2]);
    const double W[9] = {0, -o[2], o[1], o[2], 0, -o[0], -o[1], o[0], 0};
    double WW[9];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) WW[i * 3 + j] = W[i * 3] * W[j] + W[i * 3 + 1] * W[3 + j] + W[i * 3 + 2] * W[6 + j];
    double a, b, c;
    if (theta < 1e-10) {
        a = 1.0, b = 0.0, c = 0.0;  // R = I + W, V = I + W / 2
    } else {
        a = std::sin(theta) / theta, b = (1 - std::cos(theta)) / (theta * theta), c = (1 - a) / (theta * theta);
    }
    double E[16] = {0};
    for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j) {
            const double I = i == j ? 1.0 : 0.0;
            E[i * 4 + j] = theta < 1e-10 ? I + W[i * 3 + j] : I + a * W[i * 3 + j] + b * WW[i * 3 + j];
        }
        double t = 0.0;
        for (int j = 0; j < 3; ++j) {
            const double I = i == j ? 1.0 : 0.0;
            const double V = theta < 1e-10 ? I + 0.5 * W[i * 3 + j] : I + b * W[i * 3 + j] + c * WW[i * 3 + j];
            t += V * delta[3 + j];
        }
        E[i * 4 + 3] = t;
    }
    E[15] = 1.0;
    double out[16];
    for (int i = 0; i < 4; ++i)
        for (int j = 0; j < 4; ++j)
            out[i * 4 + j] = E[i * 4] * T[j] + E[i * 4 + 1] * T[4 + j] + E[i * 4 + 2] * T[8 + j] +
                             E[i * 4 + 3] * T[12 + j];
    std::copy(out, out + 16, T);
}

// Gauss-Newton on one pyramid level, at most `iterations` updates of T (in place), each from the sum of the two
// terms' normal equations (H + 1e-9 trace(H) I) delta = -g, stopping once |(omega, v / depth)| < convergence.
// terms = (photometric_floor, photometric_weight, max_association, geometric_floor, geometric_weight, huber_k).
// state (in/out) = (overlap, photometric scale, geometric scale, points used, ok): what the Python loop of
// dense_alignment.align keeps between levels; ok = 0 once a solve is ill-posed (too few points, singular or not
// finite), which stops the level.
static void dense_solve_level(int64_t n_photo, const double* P_photo, const double* I, int64_t n_geo,
                              const double* P_geo, double depth, const double* K, int h, int w, const float* grey,
                              const float* grad_x, const float* grad_y, const float* points, const float* normals,
                              const double* terms, int64_t min_points, int iterations, double convergence, double* T,
                              double* state) {
    double photo[44], geo[45];
    for (int it = 0; it < iterations; ++it) {
        dense_photometric_system(n_photo, P_photo, I, T, K, h, w, grey, grad_x, grad_y, terms[0], terms[1], terms[5],
                                 min_points, photo);
        dense_geometric_system(n_geo, P_geo, T, K, h, w, points, normals, terms[2], terms[3], terms[4], terms[5],
                               min_points, geo);
        state[0] = geo[44] / double(std::max<int64_t>(1, n_geo));
        if (photo[42] > 0) state[1] = photo[43];
        if (geo[42] > 0) state[2] = geo[43];
        const double count = photo[42] + geo[42];
        if (count < double(min_points)) {
            state[4] = 0.0;
            return;
        }
        double H[36], g[6], delta[6];
        double trace = 0.0;
        for (int k = 0; k < 36; ++k) H[k] = photo[k] + geo[k];
        for (int k = 0; k < 6; ++k) trace += H[k * 7];
        for (int k = 0; k < 6; ++k) H[k * 7] += 1e-9 * trace;
        for (int k = 0; k < 6; ++k) g[k] = -(photo[36 + k] + geo[36 + k]);
        bool finite = solve6(H, g, delta);
        for (int k = 0; k < 6 && finite; ++k) finite = std::isfinite(delta[k]);
        if (!finite) {
            state[4] = 0.0;
            return;
        }
        se3_left_update(delta, T);
        state[3] = count;
        const double rotation = std::sqrt(delta[0] * delta[0] + delta[1] * delta[1] + delta[2] * delta[2]);
        const double translation = std::sqrt(delta[3] * delta[3] + delta[4] * delta[4] + delta[5] * delta[5]) / depth;
        if (std::hypot(rotation, translation) < convergence) return;
    }
}

// One pyramid level's data for dense_align: the reference samples and the current frame's level (see
// dense_solve_level for each field). Mirrored by dense_native._Level.
struct DenseLevel {
    int64_t n_photo;
    const double* P_photo;
    const double* intensity;
    int64_t n_geo;
    const double* P_geo;
    double depth;
    double K[4];
    int64_t h, w, iterations;
    const float* grey;
    const float* grad_x;
    const float* grad_y;
    const float* points;
    const float* normals;
};

// Coarse-to-fine alignment in one call: dense_solve_level on levels[n - 1] down to levels[0], stopping at the
// first ill-posed level (state[4] = 0).
void dense_align(int n, const DenseLevel* levels, const double* terms, int64_t min_points, double convergence,
                 double* T, double* state) {
    for (int l = n - 1; l >= 0 && state[4] != 0.0; --l) {
        const DenseLevel& L = levels[l];
        dense_solve_level(L.n_photo, L.P_photo, L.intensity, L.n_geo, L.P_geo, L.depth, L.K, int(L.h), int(L.w),
                          L.grey, L.grad_x, L.grad_y, L.points, L.normals, terms, min_points, int(L.iterations),
                          convergence, T, state);
    }
}

}  // extern "C"
