// The observation-pair part of bundle adjustment's reduced camera system: S[a, b] -= Y_i W_j^T for every pair of
// observations (i, j) of one point by free keyframes a (of i) and b (of j). Plain C ABI; worker/tracking/
// schur_native.py owns the buffers and calls it through ctypes (without the GIL); the numpy reference is
// `worker.tracking.bundle_adjustment._pair_blocks_reference`.

#include <cstdint>

extern "C" {

// Y, W: [O, 6, 3] row-major float64. pair_i, pair_j: observation indices [n_pairs]; pair_a, pair_b: their free
// keyframe slots. S: [n_free * 6, n_free * 6] row-major, updated in place.
void schur_subtract_pairs(int64_t n_pairs, const int64_t* pair_i, const int64_t* pair_j, const int64_t* pair_a,
                          const int64_t* pair_b, const double* Y, const double* W, int64_t n_free, double* S) {
    const int64_t stride = 6 * n_free;
    for (int64_t k = 0; k < n_pairs; ++k) {
        const double* y = Y + 18 * pair_i[k];
        const double* w = W + 18 * pair_j[k];
        double* block = S + 6 * pair_a[k] * stride + 6 * pair_b[k];
        for (int r = 0; r < 6; ++r) {
            const double y0 = y[3 * r], y1 = y[3 * r + 1], y2 = y[3 * r + 2];
            double* row = block + r * stride;
            for (int c = 0; c < 6; ++c) row[c] -= y0 * w[3 * c] + y1 * w[3 * c + 1] + y2 * w[3 * c + 2];
        }
    }
}

}  // extern "C"
