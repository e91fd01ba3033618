/* The arm UKF's prediction and correction in C (controllers/cukf.py loads it with ctypes).
 *
 * The same maths as ArmUnscentedEstimator._predict and ._correct in numpy (the reference,
 * kept as the fallback), in plain loops over the arm's 2N-dimensional state: Merwe sigma
 * points from the Cholesky factor of (lambda + n) P, the segment ends of every sigma point
 * through the PCC chain, each visible marker gated on its own 2 x 2 innovation block, the
 * accepted markers fused together. The covariance algebra is the one numpy did; only the
 * order of the sums differs (numpy's BLAS picks its own, and uses fused multiply-adds on some
 * CPUs), so results agree to rounding, not bit for bit, with the numpy path. Built with
 * -ffp-contract=off, this code gives the same bits on every x86-64 host, which BLAS does not.
 *
 * Every buffer is the caller's (struct softhil_ukf): nothing is allocated here.
 */
#include <math.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>

#define EXPORT __attribute__((visibility("default")))

struct softhil_ukf {
    int segments;          /* N; the state has n = 2N entries: theta_1..N, omega_1..N */
    double spread;         /* lambda + n of the Merwe points */
    double noise;          /* sigma^2, the per-axis marker variance [m^2] */
    double gate;           /* chi-square gate on a marker's 2 x 2 Mahalanobis distance */
    double base[3];        /* x [m], y [m], heading [rad] */
    const double *lengths; /* N */
    const double *Wm;      /* 2n + 1 */
    const double *Wc;      /* 2n + 1 */
    /* inputs */
    const double *x;      /* n */
    const double *P;      /* n x n, row-major */
    const double *points; /* (N + 1) x 2: base marker, then segment ends; NaN where unseen */
    const double *F;      /* n x n */
    const double *G;      /* n x N */
    const double *Q;      /* n x n */
    const double *u;      /* N */
    /* outputs */
    double *x_out;        /* n */
    double *P_out;        /* n x n */
    double *y;            /* innovation: 2 m entries, m markers fused */
    double *S;            /* innovation covariance, 2m x 2m */
    int gated, measured;  /* markers gated out, markers fused */
    /* work: at least (2n + 1) (n + 4N) + 24 N N + 4 N doubles */
    double *work;
};

/* Lower Cholesky factor of the n x n row-major A into L (A = L L'); 0, or 1 if A is not
 * positive definite. The column-by-column order of LAPACK's unblocked dpotf2. */
static int cholesky(int n, const double *A, double *L) {
    for (int i = 0; i < n * n; i++) L[i] = 0.0;
    for (int j = 0; j < n; j++) {
        double d = A[j * n + j];
        for (int k = 0; k < j; k++) d -= L[j * n + k] * L[j * n + k];
        if (!(d > 0.0)) return 1; /* also NaN */
        d = sqrt(d);
        L[j * n + j] = d;
        for (int i = j + 1; i < n; i++) {
            double s = A[i * n + j];
            for (int k = 0; k < j; k++) s -= L[i * n + k] * L[j * n + k];
            L[i * n + j] = s / d;
        }
    }
    return 0;
}

/* x_out = F x + G u, P_out = F P F' + Q symmetrised. The arm's F is block diagonal (each
 * segment's theta and omega) and G has one entry a column: the terms of F's and G's zeros are
 * skipped, which leaves every sum as the dense loop forms it (a zero term adds nothing) and
 * costs a sixth of the products on six segments. */
EXPORT int softhil_ukf_predict(struct softhil_ukf *f) {
    const int N = f->segments, n = 2 * N;
    double *FP = f->work; /* n x n */
    for (int i = 0; i < n; i++) {
        double s = 0.0;
        for (int k = 0; k < n; k++)
            if (f->F[i * n + k] != 0.0) s += f->F[i * n + k] * f->x[k];
        double g = 0.0;
        for (int k = 0; k < N; k++)
            if (f->G[i * N + k] != 0.0) g += f->G[i * N + k] * f->u[k];
        f->x_out[i] = s + g;
        for (int j = 0; j < n; j++) FP[i * n + j] = 0.0;
        for (int k = 0; k < n; k++) {
            const double a = f->F[i * n + k];
            if (a == 0.0) continue;
            for (int j = 0; j < n; j++) FP[i * n + j] += a * f->P[k * n + j];
        }
    }
    for (int i = 0; i < n; i++)
        for (int j = 0; j < n; j++) {
            double t = 0.0;
            for (int k = 0; k < n; k++)
                if (f->F[j * n + k] != 0.0) t += FP[i * n + k] * f->F[j * n + k];
            f->P_out[i * n + j] = t + f->Q[i * n + j];
        }
    for (int i = 0; i < n; i++)
        for (int j = 0; j < i; j++) {
            double a = f->P_out[i * n + j], b = f->P_out[j * n + i];
            f->P_out[i * n + j] = 0.5 * (a + b);
            f->P_out[j * n + i] = 0.5 * (b + a);
        }
    return 0;
}

/* The segment-end markers of one state (theta = s[0..N-1]) into ends (N x 2), from segment
 * `from` on, the chain's pose before it in pose[3 from .. 3 from + 2] (heading, x, y); the pose
 * before each segment computed is stored there. */
static void segment_ends(const struct softhil_ukf *f, const double *s, int from, double *pose,
                         double *ends) {
    const int N = f->segments;
    double heading = pose[3 * from], px = pose[3 * from + 1], py = pose[3 * from + 2];
    for (int i = from; i < N; i++) {
        pose[3 * i] = heading;
        pose[3 * i + 1] = px;
        pose[3 * i + 2] = py;
        double theta = s[i], half = 0.5 * theta, direction = heading + half;
        double chord = f->lengths[i] * (half == 0.0 ? 1.0 : sin(half) / half);
        px += chord * cos(direction);
        py += chord * sin(direction);
        ends[2 * i] = px;
        ends[2 * i + 1] = py;
        heading += theta;
    }
}

static int same_bits(double a, double b) {
    uint64_t x, y;
    memcpy(&x, &a, sizeof x);
    memcpy(&y, &b, sizeof y);
    return x == y;
}

/* The correction by the visible markers of `points`. Returns 0 (x_out, P_out, gated, measured,
 * and where measured > 0, y and S, are set), 1 if (lambda + n) P has no Cholesky factor, or
 * 2 if the innovation covariance has none: the caller's numpy path then does what it does. */
EXPORT int softhil_ukf_correct(struct softhil_ukf *f) {
    const int N = f->segments, n = 2 * N, S_n = 2 * n + 1;
    double *w = f->work;
    double *sigmas = w;           w += (size_t)S_n * n;
    double *L = w;                w += (size_t)n * n;
    double *ends = w;             w += 2 * N;
    double *pred = w;             w += (size_t)S_n * 2 * N; /* S_n x 2V, the visible markers */
    double *dw = w;               w += (size_t)S_n * 2 * N; /* pred's deviations, weighted */
    double *zp = w;               w += 2 * N;
    double *K = w;                w += (size_t)n * 2 * N;
    double *Pxz = w;              w += (size_t)n * 2 * N;
    double *LS = w;               w += (size_t)4 * N * N;
    double *SKt = w;              w += (size_t)n * 2 * N;
    double *KSKt = w;             w += (size_t)n * n;
    int visible[64], keep[64];
    int V = 0, W = 0;
    f->gated = f->measured = 0;
    for (int i = 0; i < n; i++) f->x_out[i] = f->x[i];
    for (int i = 0; i < n * n; i++) f->P_out[i] = f->P[i];
    if (N > 64) return 1;
    for (int m = 1; m <= N; m++)
        if (!isnan(f->points[2 * m]) && !isnan(f->points[2 * m + 1])) visible[V++] = m;
    if (V == 0) return 0;
    /* sigma points: x, x + U[k], x - U[k] with U = L' (rows of U: columns of L) */
    for (int i = 0; i < n * n; i++) K[i] = f->spread * f->P[i]; /* K as scratch: spread P */
    if (cholesky(n, K, L)) return 1;
    for (int j = 0; j < n; j++) sigmas[j] = f->x[j];
    for (int k = 0; k < n; k++)
        for (int j = 0; j < n; j++) {
            sigmas[(1 + k) * n + j] = f->x[j] + L[j * n + k];
            sigmas[(1 + n + k) * n + j] = f->x[j] - L[j * n + k];
        }
    const int Z = 2 * V;
    /* The sigma points' segment ends. U is triangular, so x + U[k] and x - U[k] differ from x
     * in entries k.. only: a sigma point's segments before its first theta that differs from
     * x's (bit for bit) end where x's do, and only the rest of its chain is computed, from x's
     * pose there (half of the sigma points have x's thetas). The same operations on the same
     * values: the same bits as the whole chain. */
    double mean_pose[3 * 64], mean_ends[2 * 64], pose[3 * 64];
    mean_pose[0] = f->base[2];
    mean_pose[1] = f->base[0];
    mean_pose[2] = f->base[1];
    segment_ends(f, sigmas, 0, mean_pose, mean_ends);
    for (int s = 0; s < S_n; s++) {
        const double *sigma = sigmas + (size_t)s * n;
        int from = 0;
        while (from < N && same_bits(sigma[from], sigmas[from])) from++;
        memcpy(ends, mean_ends, sizeof(double) * 2 * (size_t)from);
        if (from < N) {
            memcpy(pose + 3 * from, mean_pose + 3 * from, sizeof(double) * 3);
            segment_ends(f, sigma, from, pose, ends);
        }
        for (int v = 0; v < V; v++) {
            pred[s * Z + 2 * v] = ends[2 * (visible[v] - 1)];
            pred[s * Z + 2 * v + 1] = ends[2 * (visible[v] - 1) + 1];
        }
    }
    for (int c = 0; c < Z; c++) {
        double t = 0.0;
        for (int s = 0; s < S_n; s++) t += f->Wm[s] * pred[s * Z + c];
        zp[c] = t;
    }
    /* Every covariance below sums (a - mean) * Wc[s] * (b - mean) over the sigma points: the
     * deviations and their weighted copies made once (pred and sigmas become them in place),
     * the same values as made in each sum, so the same bits. */
    for (int s = 0; s < S_n; s++) {
        for (int c = 0; c < Z; c++) {
            pred[s * Z + c] -= zp[c];
            dw[s * Z + c] = pred[s * Z + c] * f->Wc[s];
        }
        for (int i = 0; i < n; i++)
            sigmas[s * n + i] = (sigmas[s * n + i] - f->x[i]) * f->Wc[s];
    }
    /* the gate: each marker's 2 x 2 block of the innovation covariance, in closed form */
    for (int v = 0; v < V; v++) {
        double s00 = 0.0, s01 = 0.0, s11 = 0.0;
        for (int s = 0; s < S_n; s++) {
            const double *d = pred + s * Z + 2 * v, *e = dw + s * Z + 2 * v;
            s00 += e[0] * d[0];
            s01 += e[0] * d[1];
            s11 += e[1] * d[1];
        }
        s00 += f->noise;
        s11 += f->noise;
        const double *z = f->points + 2 * visible[v];
        double r0 = z[0] - zp[2 * v], r1 = z[1] - zp[2 * v + 1];
        double distance = (s11 * r0 * r0 - 2.0 * s01 * r0 * r1 + s00 * r1 * r1) /
                          (s00 * s11 - s01 * s01);
        if (distance <= f->gate) keep[W++] = v;
    }
    f->gated = V - W;
    if (W == 0) return 0;
    const int M = 2 * W;
    /* S = dz' diag(Wc) dz + sigma^2 I over the kept columns; Pxz = (sigmas - x)' diag(Wc) dz */
    for (int a = 0; a < M; a++) {
        int ca = 2 * keep[a / 2] + a % 2;
        for (int b = 0; b <= a; b++) {
            int cb = 2 * keep[b / 2] + b % 2;
            double t = 0.0;
            for (int s = 0; s < S_n; s++) t += dw[s * Z + ca] * pred[s * Z + cb];
            if (a == b) t += f->noise;
            f->S[a * M + b] = f->S[b * M + a] = t;
        }
        f->y[a] = f->points[2 * visible[keep[a / 2]] + a % 2] - zp[ca];
    }
    for (int i = 0; i < n; i++)
        for (int a = 0; a < M; a++) {
            int ca = 2 * keep[a / 2] + a % 2;
            double t = 0.0;
            for (int s = 0; s < S_n; s++) t += sigmas[s * n + i] * pred[s * Z + ca];
            Pxz[i * M + a] = t;
        }
    /* K = Pxz S^-1: S = LS LS', each row k of K solves S k' = Pxz[row]' */
    if (cholesky(M, f->S, LS)) return 2;
    for (int i = 0; i < n; i++) {
        double *k = K + (size_t)i * M;
        for (int a = 0; a < M; a++) { /* forward: LS z = b */
            double t = Pxz[i * M + a];
            for (int b = 0; b < a; b++) t -= LS[a * M + b] * k[b];
            k[a] = t / LS[a * M + a];
        }
        for (int a = M - 1; a >= 0; a--) { /* back: LS' k = z */
            double t = k[a];
            for (int b = a + 1; b < M; b++) t -= LS[b * M + a] * k[b];
            k[a] = t / LS[a * M + a];
        }
    }
    /* x + K y; P - K (S K') symmetrised */
    for (int i = 0; i < n; i++) {
        double t = 0.0;
        for (int a = 0; a < M; a++) t += K[i * M + a] * f->y[a];
        f->x_out[i] = f->x[i] + t;
    }
    for (int a = 0; a < M; a++)
        for (int j = 0; j < n; j++) {
            double t = 0.0;
            for (int b = 0; b < M; b++) t += f->S[a * M + b] * K[j * M + b];
            SKt[a * n + j] = t;
        }
    for (int i = 0; i < n; i++)
        for (int j = 0; j < n; j++) {
            double t = 0.0;
            for (int a = 0; a < M; a++) t += K[i * M + a] * SKt[a * n + j];
            KSKt[i * n + j] = f->P[i * n + j] - t;
        }
    for (int i = 0; i < n; i++)
        for (int j = 0; j < n; j++)
            f->P_out[i * n + j] = 0.5 * (KSKt[i * n + j] + KSKt[j * n + i]);
    f->measured = W;
    return 0;
}
