/* ArmBody physics: a whole soft arm of N piecewise-constant-curvature (PCC) segments as one
 * multibody system, so that the inertia each segment carries (the whole outer arm for the base)
 * and gravity are modelled. README.md beside this file derives the equations; in short:
 *
 * Coordinates: segment i bends by (u_i, v_i) = (theta_x, theta_y) = theta (cos gamma, sin gamma),
 * q = (u_1, v_1, u_2, v_2, ...) in space, q = (u_1, u_2, ...) in the plane (v held at 0). Its
 * transform is T = Rz(gamma) Tz(L_p) Ry(theta/2) Tz(chord) Ry(theta/2) Tz(L_p) Rz(-gamma), written
 * without gamma (no singularity at theta = 0): with T = u^2 + v^2 (the square of theta) and
 *   a(W) = sin(sqrt W) / sqrt W,  b(W) = (1 - cos(sqrt W)) / W,  c(W) = (1 - a(W)) / W,
 * a point at the fraction xi of the arc sits at r = (F u, F v, G) in the segment's base frame,
 * F = L xi^2 b(xi^2 T), G = L_p + L xi a(xi^2 T); the tip frame (after the distal L_p) is at
 * F = L b + L_p a, G = 2 L_p + L a - L_p T b, rotated by R = I + a K + b K^2, K = [phi]x,
 * phi = (-v, u, 0) (Rodrigues), whose angular velocity is J_l(phi) phi', J_l = I + b K + c K^2
 * (the left Jacobian of SO(3)). a, b, c are even and analytic: below W = SERIES_BELOW they and
 * their derivatives take their Taylor series (no 0/0, no cancellation), above it closed forms.
 *
 * Mass: each segment's mass spread uniformly along its arc, lumped at n_nodes Gauss-Legendre
 * nodes; an endplate point mass at each tip. Passive ends are massless.
 *
 * Dynamics [derived]: Lagrange's equations for the point masses m_k at p_k(q) (particle form):
 *   sum_k m_k J_k^T (J_k q'' + J'_k q') = sum_k m_k J_k^T g - K q - D q' + tau_gas + tau_ext,
 * J_k = dp_k/dq analytic, J'_k q' the velocity-product acceleration from the analytic second
 * derivatives of r and the frames' angular velocities, recursively from the base. M q'' = rhs is
 * solved by Cholesky; RK4 substeps (the glue's solver with no stiff part) integrate it.
 *
 * Actuation: each bending coordinate has its antagonistic channel pair, one closed gas circuit
 * (fmus/common/gas_circuit.h: isothermal, compliance, collapsing vacuum side) driven by the piston
 * input of its DriveCylinder; torque H(g_a) - H(g_b) (G_a (p_a - p_b) under pressure).
 *
 * Energy (outputs): E_kinetic + E_gravity + E_elastic + E_gas + E_dissipated - W_piston - W_ext and
 * E_kinetic + E_gravity + E_elastic + E_dissipated - W_actuation - W_ext are constant to the
 * integrator's accuracy. */
#include <math.h>
#include <string.h>

#include "gas_circuit.h"
#include "glue.h"

#define PI 3.14159265358979323846
#define MAX_SEGMENTS 8
#define MAX_Q (2 * MAX_SEGMENTS)
#define MAX_NODES 8
#define N_TERMS 10         /* series terms for W < 1: truncation below 1e-19 relative */
#define SERIES_BELOW 1.0   /* W = (bend angle)^2 below which a, b, c take their series */
#define PISTON_TOLERANCE 1e-9
#define SUBSTEP_AUTO_MAX 1e-3 /* [s] substep = 0 takes the stability limit, at most this */
#define RK4_RADIUS 2.5     /* RK4 is stable on the left half-disc |h lambda| <= 2.6 */

/* member i (from 0) of a per-segment family: the members' value references are consecutive */
#define SEG(inst, family, i) ((inst)->v[VR_##family##_1 + (i)])
typedef char every_family_holds_max_segments[COUNT_L == MAX_SEGMENTS ? 1 : -1];

typedef struct {
    /* the configuration, set at initialisation */
    int n_seg, n_dof, n_q, n_nodes, gas;
    double L[MAX_SEGMENTS], Lp[MAX_SEGMENTS], k[MAX_SEGMENTS], d[MAX_SEGMENTS];
    double m_node[MAX_SEGMENTS][MAX_NODES], m_end[MAX_SEGMENTS];
    double xi[MAX_NODES];                   /* Gauss-Legendre nodes on [0, 1] */
    double g[3];                            /* gravity in the base frame [m/s^2] */
    double series[N_TERMS][8];              /* Taylor coefficients in W of a, a', a'', b,
                                               b', b'', c, c' (term j of each) */
    GasCircuit circuit[MAX_SEGMENTS];       /* per segment (its G_a); n_poly = 1 */
    double gas_mass[2];                     /* sealed gas mass of side a, b (every pair) [kg] */
    double V_seal[2];                       /* their volume at sealing [m^3] */
    double T_gas;                           /* [K] */
    double theta_max;
    /* the state */
    double x[MAX_SEGMENTS][2];              /* piston position applied, per pair [m] */
    double y[2 * MAX_Q + 3];                /* q, q', E_damp, W_actuation, W_ext */
    double W_piston, E_limit, W_limit;      /* [J] */
    int resting[MAX_SEGMENTS];              /* on its limit and not moving off it (after a
                                               substep's stop; held through the next substep) */
} State;

size_t model_state_size(void) { return sizeof(State); }

/* indices of the energy integrals in y */
static int i_damp(const State *s) { return 2 * s->n_q; }
static int i_act(const State *s) { return 2 * s->n_q + 1; }
static int i_ext(const State *s) { return 2 * s->n_q + 2; }

/* ------------------------------------------------------------------ bend functions */

/* a, b, c of W and their derivatives in W: f[0] value, f[1] first, f[2] second (c: two). */
typedef struct {
    double a[3], b[3], c[2];
} Bend;

/* a, b, c and their derivatives from their Taylor series: eight Horner sums run together. */
static void bend_functions(const State *s, double W, Bend *f) {
    if (W < SERIES_BELOW) {
        /* terms for a relative truncation below 1e-16 (checked against 40-digit arithmetic) */
        const int terms = W < 0.01 ? 5 : (W < 0.1 ? 7 : N_TERMS);
        double sum[8] = {0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0};
        int j, e;
        for (j = terms - 1; j >= 0; j--)
            for (e = 0; e < 8; e++) sum[e] = sum[e] * W + s->series[j][e];
        f->a[0] = sum[0];
        f->a[1] = sum[1];
        f->a[2] = sum[2];
        f->b[0] = sum[3];
        f->b[1] = sum[4];
        f->b[2] = sum[5];
        f->c[0] = sum[6];
        f->c[1] = sum[7];
    } else {
        const double t = sqrt(W), sn = sin(t), cs = cos(t), W2 = W * W;
        f->a[0] = sn / t;
        f->a[1] = (t * cs - sn) / (2.0 * t * W);
        f->a[2] = (3.0 * sn - 3.0 * t * cs - W * sn) / (4.0 * t * W2);
        f->b[0] = (1.0 - cs) / W;
        f->b[1] = (0.5 * t * sn - 1.0 + cs) / W2;
        f->b[2] = (W * cs - 5.0 * t * sn + 8.0 - 8.0 * cs) / (4.0 * W2 * W);
        f->c[0] = (t - sn) / (t * W);
        f->c[1] = (3.0 * sn - 2.0 * t - t * cs) / (2.0 * t * W2);
    }
}

/* ------------------------------------------------------------------ kinematics and inertia */

typedef struct {
    double M[MAX_Q][MAX_Q]; /* mass matrix, both triangles [kg m^2] */
    double f[MAX_Q];        /* sum m J^T (g - J' q') [N m] */
    double tip[MAX_SEGMENTS][3];
    double E_gravity;       /* -sum m g . p [J] */
} Dynamics;

static void cross(const double a[3], const double b[3], double out[3]) {
    out[0] = a[1] * b[2] - a[2] * b[1];
    out[1] = a[2] * b[0] - a[0] * b[2];
    out[2] = a[0] * b[1] - a[1] * b[0];
}

static void rotate(const double R[3][3], const double v[3], double out[3]) {
    int i;
    for (i = 0; i < 3; i++) out[i] = R[i][0] * v[0] + R[i][1] * v[1] + R[i][2] * v[2];
}

/* R^T v */
static void rotate_back(const double R[3][3], const double v[3], double out[3]) {
    int i;
    for (i = 0; i < 3; i++) out[i] = R[0][i] * v[0] + R[1][i] * v[1] + R[2][i] * v[2];
}

static double dot(const double a[3], const double b[3]) {
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

/* The local shape functions of point k of segment i (k == n_nodes: the tip frame's origin) at
 * T = u^2 + v^2: F, F', F'' and G, G', G'' (r = (F u, F v, G)), its mass, and the bend functions
 * of the whole segment (set at the tip). */
static double point_shape(const State *s, int i, int k, double T, double F[3], double G[3],
                          Bend *whole) {
    const double L = s->L[i], Lp = s->Lp[i];
    if (k < s->n_nodes) {
        const double x = s->xi[k], x2 = x * x;
        Bend f;
        bend_functions(s, x2 * T, &f);
        F[0] = L * x2 * f.b[0];
        F[1] = L * x2 * x2 * f.b[1];
        F[2] = L * x2 * x2 * x2 * f.b[2];
        G[0] = Lp + L * x * f.a[0];
        G[1] = L * x * x2 * f.a[1];
        G[2] = L * x * x2 * x2 * f.a[2];
        return s->m_node[i][k];
    }
    bend_functions(s, T, whole);
    F[0] = L * whole->b[0] + Lp * whole->a[0];
    F[1] = L * whole->b[1] + Lp * whole->a[1];
    F[2] = L * whole->b[2] + Lp * whole->a[2];
    G[0] = 2.0 * Lp + L * whole->a[0] - Lp * T * whole->b[0];
    G[1] = L * whole->a[1] - Lp * (whole->b[0] + T * whole->b[1]);
    G[2] = L * whole->a[2] - Lp * (2.0 * whole->b[1] + T * whole->b[2]);
    return s->m_end[i];
}

/* The arm at (q, q'): M, f, the tips and the gravitational energy. A walk from the base carries
 * each segment's base frame (R, p), its angular velocity Om, the velocity-product parts of its
 * angular and linear accelerations (al, A) and its Jacobians (JO angular, JV linear, 3 x n_q).
 * A point at rho = R r from its segment's base has the Jacobian columns JV_j + JO_j x rho on the
 * coordinates before its segment's and R dr/dq_a on its own, so a segment's points enter M and f
 * through a few sums over them (the composite-body form of sum m J^T J and sum m J^T (g - a)):
 * the mass m_s, first moment c = sum m rho, inertia I_c = sum m (|rho|^2 I - rho rho^T),
 * P_a = sum m R dr_a, Q_a = sum m rho x R dr_a, the own block sum m (R dr_a) . (R dr_b), and the
 * force F = sum m w and moment N = sum m rho x w of w = g - a, the points' gravity less their
 * velocity-product acceleration:
 *   M_jl += m_s JV_j . JV_l + JV_j . (JO_l x c) + JV_l . (JO_j x c) + JO_j . I_c JO_l,
 *   M_j,a += JV_j . P_a + JO_j . Q_a,   f_j += JV_j . F + JO_j . N,   f_a += sum m R dr_a . w. */
static void spatial_dynamics(const State *s, const double q[], const double qd[],
                             Dynamics *out) {
    double R[3][3] = {{1.0, 0.0, 0.0}, {0.0, 1.0, 0.0}, {0.0, 0.0, 1.0}};
    double p[3] = {0.0, 0.0, 0.0}, Om[3] = {0.0, 0.0, 0.0}, al[3] = {0.0, 0.0, 0.0};
    double A[3] = {0.0, 0.0, 0.0};
    double JO[3][MAX_Q], JV[3][MAX_Q];
    const int nd = s->n_dof, nq = s->n_q;
    int i, j, l, k, e, a, b;
    memset(out, 0, sizeof *out);
    memset(JO, 0, sizeof JO);
    memset(JV, 0, sizeof JV);
    for (i = 0; i < s->n_seg; i++) {
        const int c0 = i * nd;
        const double u = q[c0], v = nd == 2 ? q[c0 + 1] : 0.0;
        const double ud = qd[c0], vd = nd == 2 ? qd[c0 + 1] : 0.0;
        const double T = u * u + v * v, Td = 2.0 * (u * ud + v * vd);
        const double S = 2.0 * (ud * ud + vd * vd);
        double tip_rho[3], tip_A[3], tip_u[2][3], tip_r[3] = {0.0, 0.0, 0.0};
        double tip_acc[3] = {0.0, 0.0, 0.0}, tip_dr[2][3] = {{0.0, 0.0, 0.0}, {0.0, 0.0, 0.0}};
        double A_l[3], al_l[3], Om_l[3], g_l[3], E_local = 0.0;
        /* the segment's sums over its points, about its base in its own axes (rotated to the
         * base's below) */
        double m_s = 0.0, c[3] = {0.0, 0.0, 0.0}, Ic[3][3], P[2][3], Q[2][3], own[2][2];
        double F[3] = {0.0, 0.0, 0.0}, N[3] = {0.0, 0.0, 0.0}, fo[2] = {0.0, 0.0};
        Bend tipf;
        memset(Ic, 0, sizeof Ic);
        memset(P, 0, sizeof P);
        memset(Q, 0, sizeof Q);
        memset(own, 0, sizeof own);
        rotate_back(R, A, A_l);
        rotate_back(R, al, al_l);
        rotate_back(R, Om, Om_l);
        rotate_back(R, s->g, g_l);
        for (k = 0; k <= s->n_nodes; k++) {
            /* node k of the arc, or the tip frame's origin (k == n_nodes) */
            double Fs[3], G[3], r[3], dr[2][3], rd[3], rdd[3], t1[3], t2[3], t3[3], acc[3], w[3];
            const double m = point_shape(s, i, k, T, Fs, G, &tipf);
            /* local position (F u, F v, G), its derivatives in u and v (dT/du = 2u), velocity
             * and velocity-product acceleration */
            r[0] = Fs[0] * u;
            r[1] = Fs[0] * v;
            r[2] = G[0];
            dr[0][0] = 2.0 * u * Fs[1] * u + Fs[0];
            dr[0][1] = 2.0 * u * Fs[1] * v;
            dr[0][2] = 2.0 * u * G[1];
            dr[1][0] = 2.0 * v * Fs[1] * u;
            dr[1][1] = 2.0 * v * Fs[1] * v + Fs[0];
            dr[1][2] = 2.0 * v * G[1];
            rd[0] = Fs[1] * Td * u + Fs[0] * ud;
            rd[1] = Fs[1] * Td * v + Fs[0] * vd;
            rd[2] = G[1] * Td;
            rdd[0] = (Fs[2] * Td * Td + Fs[1] * S) * u + 2.0 * Fs[1] * Td * ud;
            rdd[1] = (Fs[2] * Td * Td + Fs[1] * S) * v + 2.0 * Fs[1] * Td * vd;
            rdd[2] = G[2] * Td * Td + G[1] * S;
            /* its acceleration in the segment's frame (the base's vectors rotated into it once:
             * A_l, al_l, Om_l, g_l): a = A + al x r + Om x (Om x r) + 2 Om x r' + r'' */
            cross(al_l, r, t1);
            cross(Om_l, r, t2);
            cross(Om_l, t2, t3);
            cross(Om_l, rd, t2);
            for (e = 0; e < 3; e++) {
                acc[e] = A_l[e] + t1[e] + t3[e] + 2.0 * t2[e] + rdd[e];
                w[e] = g_l[e] - acc[e];
            }
            if (k == s->n_nodes) {
                for (e = 0; e < 3; e++) {
                    tip_r[e] = r[e];
                    tip_acc[e] = acc[e];
                    for (a = 0; a < nd; a++) tip_dr[a][e] = dr[a][e];
                }
            }
            if (m == 0.0) continue;
            {
                const double rr = dot(r, r);
                m_s += m;
                for (e = 0; e < 3; e++) {
                    c[e] += m * r[e];
                    F[e] += m * w[e];
                    for (l = 0; l < 3; l++) Ic[e][l] -= m * r[e] * r[l];
                    Ic[e][e] += m * rr;
                }
                cross(r, w, t1);
                for (e = 0; e < 3; e++) N[e] += m * t1[e];
                for (a = 0; a < nd; a++) {
                    cross(r, dr[a], t1);
                    for (e = 0; e < 3; e++) {
                        P[a][e] += m * dr[a][e];
                        Q[a][e] += m * t1[e];
                    }
                    fo[a] += m * dot(dr[a], w);
                    for (b = a; b < nd; b++) own[a][b] += m * dot(dr[a], dr[b]);
                }
                E_local -= m * dot(g_l, r);
            }
        }
        /* the sums to the base's axes: vectors by R, the inertia by R I_c R^T */
        {
            double t[3][3], v3[3];
            rotate(R, c, v3);
            memcpy(c, v3, sizeof c);
            rotate(R, F, v3);
            memcpy(F, v3, sizeof F);
            rotate(R, N, v3);
            memcpy(N, v3, sizeof N);
            for (a = 0; a < nd; a++) {
                rotate(R, P[a], v3);
                memcpy(P[a], v3, sizeof v3);
                rotate(R, Q[a], v3);
                memcpy(Q[a], v3, sizeof v3);
                rotate(R, tip_dr[a], tip_u[a]);
            }
            for (e = 0; e < 3; e++)
                for (l = 0; l < 3; l++)
                    t[e][l] = Ic[e][0] * R[l][0] + Ic[e][1] * R[l][1] + Ic[e][2] * R[l][2];
            for (e = 0; e < 3; e++)
                for (l = 0; l < 3; l++)
                    Ic[e][l] = R[e][0] * t[0][l] + R[e][1] * t[1][l] + R[e][2] * t[2][l];
            rotate(R, tip_r, tip_rho);
            rotate(R, tip_acc, tip_A);
            out->E_gravity += E_local - m_s * dot(s->g, p);
        }
        /* the segment's points into M and f */
        {
            double cx[MAX_Q][3], Io[MAX_Q][3]; /* JO_j x c and I_c JO_j */
            for (j = 0; j < c0; j++) {
                const double JOj[3] = {JO[0][j], JO[1][j], JO[2][j]};
                cross(JOj, c, cx[j]);
                rotate((const double(*)[3])Ic, JOj, Io[j]);
            }
            for (j = 0; j < c0; j++) {
                const double JVj[3] = {JV[0][j], JV[1][j], JV[2][j]};
                const double JOj[3] = {JO[0][j], JO[1][j], JO[2][j]};
                for (l = j; l < c0; l++) {
                    const double JVl[3] = {JV[0][l], JV[1][l], JV[2][l]};
                    out->M[j][l] += m_s * dot(JVj, JVl) + dot(JVj, cx[l]) + dot(JVl, cx[j]) +
                                    dot(JOj, Io[l]);
                }
                for (a = 0; a < nd; a++) out->M[j][c0 + a] += dot(JVj, P[a]) + dot(JOj, Q[a]);
                out->f[j] += dot(JVj, F) + dot(JOj, N);
            }
        }
        for (a = 0; a < nd; a++) {
            for (b = a; b < nd; b++) out->M[c0 + a][c0 + b] += own[a][b];
            out->f[c0 + a] += fo[a];
        }
        /* the next segment's base frame: R_loc = I + a K + b K^2, angular velocity J_l phi' with
         * phi = (-v, u, 0) (columns J_l e_y for u, -J_l e_x for v), and the velocity-product part
         * of its derivative, b' T' (phi x phi') + c' T' phi x (phi x phi') + c phi' x (phi x phi'),
         * with phi x phi' = (0, 0, u v' - v u') */
        {
            const double ta = tipf.a[0], tb = tipf.b[0], tc = tipf.c[0];
            const double w3 = u * vd - v * ud;
            const double Rl[3][3] = {{1.0 - tb * u * u, -tb * u * v, ta * u},
                                     {-tb * u * v, 1.0 - tb * v * v, ta * v},
                                     {-ta * u, -ta * v, 1.0 - tb * T}};
            const double col[2][3] = {{-tc * u * v, 1.0 - tc * v * v, -tb * v},
                                      {-1.0 + tc * u * u, tc * u * v, tb * u}};
            const double al_loc[3] = {tipf.c[1] * Td * w3 * u + tc * w3 * ud,
                                      tipf.c[1] * Td * w3 * v + tc * w3 * vd,
                                      tipf.b[1] * Td * w3};
            double w_loc[3], Rw[3], t1[3], t2[3], Rn[3][3];
            /* the tip's linear Jacobian first (it reads JO before the own columns are set) */
            for (j = 0; j < c0; j++) {
                const double JOj[3] = {JO[0][j], JO[1][j], JO[2][j]};
                cross(JOj, tip_rho, t1);
                for (e = 0; e < 3; e++) JV[e][j] += t1[e];
            }
            for (a = 0; a < nd; a++)
                for (e = 0; e < 3; e++) JV[e][c0 + a] = tip_u[a][e];
            for (e = 0; e < 3; e++) w_loc[e] = col[0][e] * ud + col[1][e] * vd;
            rotate(R, w_loc, Rw);
            cross(Om, Rw, t1);
            rotate(R, al_loc, t2);
            for (e = 0; e < 3; e++) {
                al[e] += t1[e] + t2[e];
                Om[e] += Rw[e];
            }
            for (a = 0; a < nd; a++) {
                rotate(R, col[a], t1);
                for (e = 0; e < 3; e++) JO[e][c0 + a] = t1[e];
            }
            for (e = 0; e < 3; e++)
                for (l = 0; l < 3; l++)
                    Rn[e][l] = R[e][0] * Rl[0][l] + R[e][1] * Rl[1][l] + R[e][2] * Rl[2][l];
            memcpy(R, Rn, sizeof R);
            for (e = 0; e < 3; e++) {
                p[e] += tip_rho[e];
                A[e] = tip_A[e];
                out->tip[i][e] = p[e];
            }
        }
    }
    for (j = 0; j < nq; j++)
        for (l = 0; l < j; l++) out->M[j][l] = out->M[l][j];
}

/* The planar arm (v = 0): spatial_dynamics with every frame turned about y by the sum psi of the
 * bends before it, so that every angular Jacobian column is e_y, the angular velocity-product
 * acceleration vanishes and the sums reduce to the plane's (x, z): the same equations in less
 * arithmetic (checked against the spatial path in tests/test_arm_body.py). With
 * e_y x (x, z) = (z, -x) and h = e_y x c:
 *   M_jl += m_s JV_j . JV_l + (JV_j + JV_l) . h + I_yy,  M_j,a += JV_j . P + Q_y,
 *   f_j += JV_j . F + N_y,  I_yy = sum m |r|^2, Q_y = sum m (r x dr)_y, N_y = sum m (r x w)_y. */
static void planar_dynamics(const State *s, const double q[], const double qd[], Dynamics *out) {
    double psi = 0.0, Om = 0.0, p[2] = {0.0, 0.0}, A[2] = {0.0, 0.0}, JV[2][MAX_Q];
    const int nq = s->n_q;
    int i, j, l, k;
    memset(out, 0, sizeof *out);
    for (i = 0; i < s->n_seg; i++) {
        const double u = q[i], ud = qd[i], T = u * u, Td = 2.0 * u * ud, S = 2.0 * ud * ud;
        const double cp = cos(psi), sp = sin(psi);
        /* the base's vectors in the segment's axes (R^T, R = Ry(psi)) */
        const double A_l[2] = {cp * A[0] - sp * A[1], sp * A[0] + cp * A[1]};
        const double g_l[2] = {cp * s->g[0] - sp * s->g[2], sp * s->g[0] + cp * s->g[2]};
        double m_s = 0.0, c[2] = {0.0, 0.0}, Iyy = 0.0, P[2] = {0.0, 0.0}, Qy = 0.0, own = 0.0;
        double F[2] = {0.0, 0.0}, Ny = 0.0, fo = 0.0, E_local = 0.0;
        double tip_r[2] = {0.0, 0.0}, tip_acc[2] = {0.0, 0.0}, tip_dr[2] = {0.0, 0.0};
        Bend whole;
        for (k = 0; k <= s->n_nodes; k++) {
            double Fs[3], G[3], r[2], dr[2], rd[2], rdd[2], acc[2], w[2];
            const double m = point_shape(s, i, k, T, Fs, G, &whole);
            r[0] = Fs[0] * u;
            r[1] = G[0];
            dr[0] = 2.0 * u * Fs[1] * u + Fs[0];
            dr[1] = 2.0 * u * G[1];
            rd[0] = Fs[1] * Td * u + Fs[0] * ud;
            rd[1] = G[1] * Td;
            rdd[0] = (Fs[2] * Td * Td + Fs[1] * S) * u + 2.0 * Fs[1] * Td * ud;
            rdd[1] = G[2] * Td * Td + G[1] * S;
            /* a = A + Om x (Om x r) + 2 Om x r' + r'' with Om = (0, Om, 0) */
            acc[0] = A_l[0] - Om * Om * r[0] + 2.0 * Om * rd[1] + rdd[0];
            acc[1] = A_l[1] - Om * Om * r[1] - 2.0 * Om * rd[0] + rdd[1];
            w[0] = g_l[0] - acc[0];
            w[1] = g_l[1] - acc[1];
            if (k == s->n_nodes) {
                tip_r[0] = r[0];
                tip_r[1] = r[1];
                tip_acc[0] = acc[0];
                tip_acc[1] = acc[1];
                tip_dr[0] = dr[0];
                tip_dr[1] = dr[1];
            }
            if (m == 0.0) continue;
            m_s += m;
            c[0] += m * r[0];
            c[1] += m * r[1];
            Iyy += m * (r[0] * r[0] + r[1] * r[1]);
            P[0] += m * dr[0];
            P[1] += m * dr[1];
            Qy += m * (r[1] * dr[0] - r[0] * dr[1]);
            own += m * (dr[0] * dr[0] + dr[1] * dr[1]);
            F[0] += m * w[0];
            F[1] += m * w[1];
            Ny += m * (r[1] * w[0] - r[0] * w[1]);
            fo += m * (dr[0] * w[0] + dr[1] * w[1]);
            E_local -= m * (g_l[0] * r[0] + g_l[1] * r[1]);
        }
        {
            /* the sums to the base's axes (R = Ry(psi): (x, z) -> (c x + s z, -s x + c z)) */
            const double cw[2] = {cp * c[0] + sp * c[1], -sp * c[0] + cp * c[1]};
            const double Pw[2] = {cp * P[0] + sp * P[1], -sp * P[0] + cp * P[1]};
            const double Fw[2] = {cp * F[0] + sp * F[1], -sp * F[0] + cp * F[1]};
            const double h[2] = {cw[1], -cw[0]};
            const double tip_rho[2] = {cp * tip_r[0] + sp * tip_r[1],
                                       -sp * tip_r[0] + cp * tip_r[1]};
            for (j = 0; j < i; j++) {
                const double hj = JV[0][j] * h[0] + JV[1][j] * h[1];
                for (l = j; l < i; l++)
                    out->M[j][l] += m_s * (JV[0][j] * JV[0][l] + JV[1][j] * JV[1][l]) + hj +
                                    JV[0][l] * h[0] + JV[1][l] * h[1] + Iyy;
                out->M[j][i] += JV[0][j] * Pw[0] + JV[1][j] * Pw[1] + Qy;
                out->f[j] += JV[0][j] * Fw[0] + JV[1][j] * Fw[1] + Ny;
            }
            out->M[i][i] += own;
            out->f[i] += fo;
            out->E_gravity += E_local - m_s * (s->g[0] * p[0] + s->g[2] * p[1]);
            /* the next base: JV_j + e_y x rho_tip, its own column R dr, A, p, psi, Om */
            for (j = 0; j < i; j++) {
                JV[0][j] += tip_rho[1];
                JV[1][j] -= tip_rho[0];
            }
            JV[0][i] = cp * tip_dr[0] + sp * tip_dr[1];
            JV[1][i] = -sp * tip_dr[0] + cp * tip_dr[1];
            A[0] = cp * tip_acc[0] + sp * tip_acc[1];
            A[1] = -sp * tip_acc[0] + cp * tip_acc[1];
            p[0] += tip_rho[0];
            p[1] += tip_rho[1];
            out->tip[i][0] = p[0];
            out->tip[i][2] = p[1];
            psi += u;
            Om += ud;
        }
    }
    for (j = 0; j < nq; j++)
        for (l = 0; l < j; l++) out->M[j][l] = out->M[l][j];
}

static void arm_dynamics(const State *s, const double q[], const double qd[], Dynamics *out) {
    if (s->n_dof == 1)
        planar_dynamics(s, q, qd, out);
    else
        spatial_dynamics(s, q, qd, out);
}

/* Cholesky factor of the symmetric positive definite n x n A (lower triangle in Lc); 0 if A is
 * not positive definite. */
static int cholesky(int n, const double A[MAX_Q][MAX_Q], double Lc[MAX_Q][MAX_Q]) {
    int i, j, k;
    for (i = 0; i < n; i++)
        for (j = 0; j <= i; j++) {
            double sum = A[i][j];
            for (k = 0; k < j; k++) sum -= Lc[i][k] * Lc[j][k];
            if (i == j) {
                if (!(sum > 0.0)) return 0;
                Lc[i][i] = sqrt(sum);
            } else {
                Lc[i][j] = sum / Lc[j][j];
            }
        }
    return 1;
}

/* Solves Lc Lc^T x = b in place. */
static void cholesky_solve(int n, const double Lc[MAX_Q][MAX_Q], double x[]) {
    int i, k;
    for (i = 0; i < n; i++) {
        for (k = 0; k < i; k++) x[i] -= Lc[i][k] * x[k];
        x[i] /= Lc[i][i];
    }
    for (i = n - 1; i >= 0; i--) {
        for (k = i + 1; k < n; k++) x[i] -= Lc[k][i] * x[k];
        x[i] /= Lc[i][i];
    }
}

/* ------------------------------------------------------------------ the gas */

/* The pair acting on coordinate j (segment j / n_dof, axis j % n_dof) at bend theta and piston
 * position x; 0 if it has no physical state. */
static int pair_state(const State *s, int j, double theta, double x, GasState *gas) {
    const double theta_s[2] = {s->T_gas, s->T_gas};
    return gas_state(&s->circuit[j / s->n_dof], x, theta, s->gas_mass, theta_s, gas);
}

static double piston_of(const State *s, int j) { return s->x[j / s->n_dof][j % s->n_dof]; }

/* Energy stored in a pair's gas (isothermal free energy relative to its sealed state,
 * p_atm V_s r - m R T ln(1 + r) with r = V / V_s - 1, never negative) and channel walls [J]. */
static double pair_energy(const State *s, int j, double theta, const GasState *gas) {
    double total = 0.0;
    int side;
    for (side = 0; side < 2; side++) {
        const double r = gas->V[side] / s->V_seal[side] - 1.0;
        const double mRT = s->gas_mass[side] * s->circuit[0].R_gas * s->T_gas;
        total += s->circuit[0].p_atm * s->V_seal[side] * r - mRT * log1p(r) +
                 gas_membrane_energy(&s->circuit[j / s->n_dof], gas, side, theta);
    }
    return total;
}

/* The gas torques on every coordinate at q and the pistons' positions, and (if energy is not
 * NULL) the gas's stored energy; 0 if a pair has no physical state. */
static int gas_torques(const State *s, const double q[], double tau[], double *energy) {
    int j;
    if (energy) *energy = 0.0;
    for (j = 0; j < s->n_q; j++) {
        GasState gas;
        tau[j] = 0.0;
        if (!s->gas) continue;
        if (!pair_state(s, j, q[j], piston_of(s, j), &gas)) return 0;
        tau[j] = gas_bending_torque(&gas);
        if (energy) *energy += pair_energy(s, j, q[j], &gas);
    }
    return 1;
}

static double external_torque(const Instance *inst, const State *s, int j) {
    return j % s->n_dof == 0 ? SEG(inst, tau_ext_x, j / s->n_dof)
                             : SEG(inst, tau_ext_y, j / s->n_dof);
}

/* ------------------------------------------------------------------ equations of motion */

/* Segment i's bend (u, v) = q[i n_dof ...]: its angle and the limit's outward normal n. */
static double bend_and_normal(const State *s, const double q[], int i, double normal[2]) {
    const int nd = s->n_dof;
    const double u = q[i * nd], v = nd == 2 ? q[i * nd + 1] : 0.0, theta = sqrt(u * u + v * v);
    normal[0] = theta > 0.0 ? u / theta : 0.0;
    normal[1] = theta > 0.0 ? v / theta : 0.0;
    return theta;
}

/* The segments on the mechanical limit |theta_i| = theta_max, as contacts: those marked in
 * `only`, or without it those within LIMIT_BAND of the limit; each one's outward normal n_a in the
 * coordinates (the unit bend direction of its segment) and M^-1 n_a (from the Cholesky factor
 * Lc), and A = N^T M^-1 N. */
#define LIMIT_BAND 1e-6 /* [rad] */
typedef struct {
    int m, seg[MAX_SEGMENTS];
    double normal[MAX_SEGMENTS][2], theta[MAX_SEGMENTS];
    double Z[MAX_SEGMENTS][MAX_Q];
    double A[MAX_SEGMENTS][MAX_SEGMENTS];
} Contacts;

static void find_contacts(const State *s, const double q[], const double Lc[MAX_Q][MAX_Q],
                          const int only[], Contacts *c) {
    const int nd = s->n_dof, n = s->n_q;
    int i, j, a;
    c->m = 0;
    for (i = 0; i < s->n_seg; i++) {
        double *nrm = c->normal[c->m], *z = c->Z[c->m];
        const double theta = bend_and_normal(s, q, i, nrm);
        if (only ? !only[i] : theta < s->theta_max - LIMIT_BAND) continue;
        for (j = 0; j < n; j++) z[j] = 0.0;
        for (j = 0; j < nd; j++) z[i * nd + j] = nrm[j];
        cholesky_solve(n, Lc, z);
        c->seg[c->m] = i;
        c->theta[c->m] = theta;
        c->m++;
    }
    for (a = 0; a < c->m; a++)
        for (i = 0; i < c->m; i++) {
            c->A[a][i] = 0.0;
            for (j = 0; j < nd; j++) c->A[a][i] += c->normal[a][j] * c->Z[i][c->seg[a] * nd + j];
        }
}

/* The contacts' reactions lambda >= 0 with b - A lambda <= 0 for every contact taking part
 * (`part`), and = 0 where lambda > 0 (an inelastic contact: what would move a segment beyond its
 * limit, b > 0, is stopped; nothing pulls it back), by an active set: solve for the active ones,
 * drop a negative one, add one the others push outwards, until neither happens. */
static void contact_reactions(const Contacts *c, const int part[], const double b[],
                              double lambda[]) {
    int active[MAX_SEGMENTS], a, l, i, iteration;
    for (a = 0; a < c->m; a++) {
        active[a] = part[a] && b[a] > 0.0;
        lambda[a] = 0.0;
    }
    for (iteration = 0; iteration < 4 * MAX_SEGMENTS; iteration++) {
        double Aa[MAX_SEGMENTS][MAX_SEGMENTS], x[MAX_SEGMENTS];
        int index[MAX_SEGMENTS], k = 0, changed = 0, worst = -1;
        for (a = 0; a < c->m; a++)
            if (active[a]) index[k++] = a;
        for (a = 0; a < k; a++) {
            x[a] = b[index[a]];
            for (l = 0; l < k; l++) Aa[a][l] = c->A[index[a]][index[l]];
        }
        /* Gaussian elimination without pivoting: A is symmetric positive definite */
        for (a = 0; a < k; a++)
            for (l = a + 1; l < k; l++) {
                const double f = Aa[l][a] / Aa[a][a];
                for (i = a; i < k; i++) Aa[l][i] -= f * Aa[a][i];
                x[l] -= f * x[a];
            }
        for (a = k - 1; a >= 0; a--) {
            for (l = a + 1; l < k; l++) x[a] -= Aa[a][l] * x[l];
            x[a] /= Aa[a][a];
        }
        for (a = 0; a < c->m; a++) lambda[a] = 0.0;
        for (a = 0; a < k; a++) {
            lambda[index[a]] = x[a];
            if (x[a] < 0.0 && (worst < 0 || x[a] < lambda[worst])) worst = index[a];
        }
        if (worst >= 0) {
            active[worst] = 0;
            continue;
        }
        for (a = 0; a < c->m; a++) {
            double residual = b[a];
            if (active[a] || !part[a]) continue;
            for (l = 0; l < c->m; l++) residual -= c->A[a][l] * lambda[l];
            if (residual > 0.0) {
                active[a] = changed = 1;
                break;
            }
        }
        if (!changed) break;
    }
}

/* A segment resting on its limit (State.resting, decided at the end of the previous substep)
 * takes the reaction -lambda n that keeps it there: g = |q_i| - theta_max, g'' = n . q_i'' +
 * (|q_i'|^2 - (n . q_i')^2) / theta = 0, lambda >= 0. Which segments rest is held through a
 * substep: decided stage by stage (by the stage's bend, which leaves the limit's circle by about
 * v_t^2 h^2 / theta at a tangential rate v_t), a reaction switching on or off between RK4's
 * stages would make the right-hand side jump (a first-order error in the energy); a segment
 * arriving is left free until the end of its substep, where model_after_substep stops it.
 * acc, the free acceleration, is corrected in place. The reactions do no work (n . q_i' = 0
 * while a segment rests; what they do on the integrator's drift off the limit is within its
 * error). */
static void limit_reactions(const State *s, const double q[], const double qd[],
                            const double Lc[MAX_Q][MAX_Q], double acc[]) {
    const int nd = s->n_dof, n = s->n_q;
    Contacts c;
    double b[MAX_SEGMENTS] = {0.0}, lambda[MAX_SEGMENTS];
    int part[MAX_SEGMENTS] = {0}, a, j;
    find_contacts(s, q, Lc, s->resting, &c);
    if (c.m == 0) return;
    for (a = 0; a < c.m; a++) {
        const int i = c.seg[a];
        double speed2 = 0.0, rate = 0.0;
        for (j = 0; j < nd; j++) {
            rate += c.normal[a][j] * qd[i * nd + j];
            speed2 += qd[i * nd + j] * qd[i * nd + j];
        }
        b[a] = (speed2 - rate * rate) / c.theta[a];
        for (j = 0; j < nd; j++) b[a] += c.normal[a][j] * acc[i * nd + j];
        part[a] = 1;
    }
    contact_reactions(&c, part, b, lambda);
    for (a = 0; a < c.m; a++)
        for (j = 0; j < n; j++) acc[j] -= lambda[a] * c.Z[a][j];
}

int model_derivatives(const Instance *inst, const double y[], double dy[]) {
    const State *s = (const State *)inst->state;
    const int n = s->n_q;
    const double *q = y, *qd = y + n;
    Dynamics dyn;
    double Lc[MAX_Q][MAX_Q], tau[MAX_Q], acc[MAX_Q];
    double damping = 0.0, actuation = 0.0, external = 0.0;
    int j;
    arm_dynamics(s, q, qd, &dyn);
    if (!gas_torques(s, q, tau, NULL)) return 0;
    for (j = 0; j < n; j++) {
        const double te = external_torque(inst, s, j), d = s->d[j / s->n_dof];
        acc[j] = dyn.f[j] - s->k[j / s->n_dof] * q[j] - d * qd[j] + tau[j] + te;
        damping += d * qd[j] * qd[j];
        actuation += tau[j] * qd[j];
        external += te * qd[j];
    }
    if (!cholesky(n, (const double(*)[MAX_Q])dyn.M, Lc)) return 0;
    cholesky_solve(n, (const double(*)[MAX_Q])Lc, acc);
    limit_reactions(s, q, qd, (const double(*)[MAX_Q])Lc, acc);
    for (j = 0; j < n; j++) {
        dy[j] = qd[j];
        dy[n + j] = acc[j];
    }
    dy[i_damp(s)] = damping;
    dy[i_act(s)] = actuation;
    dy[i_ext(s)] = external;
    return 1;
}

/* Kinetic energy 1/2 q'^T M q' [J]. */
static double kinetic_energy(const State *s, const Dynamics *dyn, const double qd[]) {
    double total = 0.0;
    int j, l;
    for (j = 0; j < s->n_q; j++)
        for (l = 0; l < s->n_q; l++) total += 0.5 * qd[j] * dyn->M[j][l] * qd[l];
    return total;
}

static double elastic_energy(const State *s, const double q[]) {
    double total = 0.0;
    int j;
    for (j = 0; j < s->n_q; j++) total += 0.5 * s->k[j / s->n_dof] * q[j] * q[j];
    return total;
}

/* What is stored: mechanical (kinetic, gravitational, elastic) and in the gas [J]; 0 without a
 * gas state. */
static int stored_energy(const State *s, const double y[], double *mechanical, double *gas) {
    Dynamics dyn;
    double tau[MAX_Q];
    arm_dynamics(s, y, y + s->n_q, &dyn);
    if (!gas_torques(s, y, tau, gas)) return 0;
    *mechanical = kinetic_energy(s, &dyn, y + s->n_q) + dyn.E_gravity + elastic_energy(s, y);
    return 1;
}

/* The mechanical limit |theta_i| <= theta_max after a substep: a segment beyond it (arriving, or
 * the integrator's drift while it rests there) is put back on it, and the segments on it (within
 * LIMIT_BAND) that move outwards are stopped together by inelastic impulses along their normals
 * (the contact problem of limit_reactions on the velocities). The energy this takes is counted
 * as dissipated (E_limit), and the work the gas did on the arm moved back as actuation (W_limit).
 * The segments on it left moving by less than LIMIT_RATE along their normal rest through the next
 * substep. */
#define LIMIT_RATE 1e-6 /* [rad/s] */
static void stop_at_limit(State *s) {
    const int nd = s->n_dof, n = s->n_q;
    const double limit = s->theta_max;
    double *q = s->y, *qd = s->y + n, mech_before, gas_before, mech_after, gas_after;
    int i, j, a, near = 0, known;
    for (i = 0; i < s->n_seg; i++) {
        double nrm[2];
        s->resting[i] = 0;
        if (bend_and_normal(s, q, i, nrm) >= limit - LIMIT_BAND) near = 1;
    }
    if (!near) return;
    known = stored_energy(s, s->y, &mech_before, &gas_before);
    for (i = 0; i < s->n_seg; i++) {
        double nrm[2];
        const double theta = bend_and_normal(s, q, i, nrm);
        if (theta > limit)
            for (j = 0; j < nd; j++) q[i * nd + j] *= limit / theta;
    }
    {
        Dynamics dyn;
        Contacts c;
        double Lc[MAX_Q][MAX_Q], b[MAX_SEGMENTS] = {0.0}, impulse[MAX_SEGMENTS];
        int part[MAX_SEGMENTS] = {0};
        arm_dynamics(s, q, qd, &dyn);
        if (cholesky(n, (const double(*)[MAX_Q])dyn.M, Lc)) {
            find_contacts(s, q, (const double(*)[MAX_Q])Lc, NULL, &c);
            for (a = 0; a < c.m; a++) {
                for (j = 0; j < nd; j++) b[a] += c.normal[a][j] * qd[c.seg[a] * nd + j];
                part[a] = 1;
            }
            contact_reactions(&c, part, b, impulse);
            for (a = 0; a < c.m; a++)
                for (j = 0; j < n; j++) qd[j] -= impulse[a] * c.Z[a][j];
            for (a = 0; a < c.m; a++) {
                double rate = 0.0;
                for (j = 0; j < nd; j++) rate += c.normal[a][j] * qd[c.seg[a] * nd + j];
                s->resting[c.seg[a]] = fabs(rate) <= LIMIT_RATE;
            }
        }
    }
    if (known && stored_energy(s, s->y, &mech_after, &gas_after)) {
        s->E_limit += mech_before + gas_before - mech_after - gas_after;
        s->W_limit += gas_before - gas_after;
    }
}

void model_after_substep(Instance *inst, double dt) {
    (void)dt;
    stop_at_limit((State *)inst->state);
}

double model_time_to_event(const Instance *inst) {
    (void)inst;
    return INFINITY;
}

void model_discrete_update(Instance *inst) { (void)inst; }

/* ------------------------------------------------------------------ inputs and outputs */

/* The piston input of the pair on coordinate j, within the stroke: a rounding-sized excursion
 * (PISTON_TOLERANCE x stroke) is clamped silently, a larger one is an error. */
static int applied_piston_position(Instance *inst, const State *s, int j, double *x) {
    const int i = j / s->n_dof, axis = j % s->n_dof;
    const double raw = axis == 0 ? SEG(inst, x_piston_x, i) : SEG(inst, x_piston_y, i);
    const double stroke = s->circuit[i].stroke, tolerance = PISTON_TOLERANCE * stroke;
    if (raw < -tolerance || raw > stroke + tolerance) {
        log_message(inst, fmi2Error,
                    "input x_piston_%c_%d = %.10g is outside the stroke [0, %g] (tolerance %g m)",
                    axis == 0 ? 'x' : 'y', i + 1, raw, stroke, tolerance);
        return 0;
    }
    *x = raw < 0.0 ? 0.0 : (raw > stroke ? stroke : raw);
    return 1;
}

/* New piston positions are a sudden (isothermal, the gas's only law here) compression: the work
 * done on the gas is the change of its stored energy at a fixed bend. */
fmi2Status model_step_start(Instance *inst) {
    State *s = (State *)inst->state;
    int j;
    if (!s->gas) return fmi2OK;
    for (j = 0; j < s->n_q; j++) {
        const int i = j / s->n_dof, axis = j % s->n_dof;
        const double theta = s->y[j];
        GasState before, after;
        double x;
        if (!applied_piston_position(inst, s, j, &x)) return fmi2Error;
        if (x == s->x[i][axis]) continue;
        if (!pair_state(s, j, theta, s->x[i][axis], &before) ||
            !pair_state(s, j, theta, x, &after)) {
            log_message(inst, fmi2Error,
                        "no physical gas state at piston position %g m (segment %d, pair %c)", x,
                        i + 1, axis == 0 ? 'x' : 'y');
            return fmi2Error;
        }
        s->W_piston += pair_energy(s, j, theta, &after) - pair_energy(s, j, theta, &before);
        s->x[i][axis] = x;
    }
    return fmi2OK;
}

fmi2Status model_outputs(Instance *inst) {
    State *s = (State *)inst->state;
    const int n = s->n_q, nd = s->n_dof;
    const double *q = s->y, *qd = s->y + n;
    Dynamics dyn;
    double E_gas = 0.0;
    int i, j;
    arm_dynamics(s, q, qd, &dyn);
    for (i = 0; i < MAX_SEGMENTS; i++) {
        const int used = i < s->n_seg;
        const double u = used ? q[i * nd] : 0.0, v = used && nd == 2 ? q[i * nd + 1] : 0.0;
        SEG(inst, theta_x, i) = u;
        SEG(inst, theta_y, i) = v;
        SEG(inst, theta, i) = sqrt(u * u + v * v);
        SEG(inst, kappa, i) = used ? sqrt(u * u + v * v) / s->L[i] : 0.0;
        SEG(inst, kappa_x, i) = used ? u / s->L[i] : 0.0;
        SEG(inst, theta_dot_x, i) = used ? qd[i * nd] : 0.0;
        SEG(inst, theta_dot_y, i) = used && nd == 2 ? qd[i * nd + 1] : 0.0;
        SEG(inst, tip_x, i) = used ? dyn.tip[i][0] : 0.0;
        SEG(inst, tip_y, i) = used ? dyn.tip[i][1] : 0.0;
        SEG(inst, tip_z, i) = used ? dyn.tip[i][2] : 0.0;
        SEG(inst, p_a_x, i) = SEG(inst, p_b_x, i) = SEG(inst, v_a_x, i) = SEG(inst, v_b_x, i) = 0.0;
        SEG(inst, p_a_y, i) = SEG(inst, p_b_y, i) = SEG(inst, v_a_y, i) = SEG(inst, v_b_y, i) = 0.0;
    }
    for (j = 0; s->gas && j < n; j++) {
        const int i = j / nd;
        GasState gas;
        if (!pair_state(s, j, q[j], piston_of(s, j), &gas)) {
            log_message(inst, fmi2Error,
                        "no physical gas state (segment %d, pair %c: bend %g rad, piston %g m): a "
                        "volume collapsed",
                        i + 1, j % nd == 0 ? 'x' : 'y', q[j], piston_of(s, j));
            return fmi2Error;
        }
        E_gas += pair_energy(s, j, q[j], &gas);
        if (j % nd == 0) {
            SEG(inst, p_a_x, i) = gas.g[0];
            SEG(inst, p_b_x, i) = gas.g[1];
            SEG(inst, v_a_x, i) = gas.V[0];
            SEG(inst, v_b_x, i) = gas.V[1];
        } else {
            SEG(inst, p_a_y, i) = gas.g[0];
            SEG(inst, p_b_y, i) = gas.g[1];
            SEG(inst, v_a_y, i) = gas.V[0];
            SEG(inst, v_b_y, i) = gas.V[1];
        }
    }
    V(inst, E_kinetic) = kinetic_energy(s, &dyn, qd);
    V(inst, E_gravity) = dyn.E_gravity;
    V(inst, E_elastic) = elastic_energy(s, q);
    V(inst, E_gas) = E_gas;
    V(inst, E_dissipated) = s->y[i_damp(s)] + s->E_limit;
    V(inst, W_actuation) = s->y[i_act(s)] + s->W_limit;
    V(inst, W_ext) = s->y[i_ext(s)];
    V(inst, W_piston) = s->W_piston;
    V(inst, M_11) = dyn.M[0][0];
    return fmi2OK;
}

/* ------------------------------------------------------------------ initialisation */

/* Gauss-Legendre nodes xi and weights w (summing to 1) of n points on [0, 1]: Newton on the
 * Legendre polynomial P_n from Tricomi's estimate of its roots. */
static void gauss_legendre(int n, double xi[], double w[]) {
    int i, j, iteration;
    for (i = 0; i < (n + 1) / 2; i++) {
        double z = cos(PI * (i + 0.75) / (n + 0.5)), pp = 1.0;
        for (iteration = 0; iteration < 100; iteration++) {
            double p1 = 1.0, p2 = 0.0, z1;
            for (j = 1; j <= n; j++) {
                const double p3 = p2;
                p2 = p1;
                p1 = ((2.0 * j - 1.0) * z * p2 - (j - 1.0) * p3) / j;
            }
            pp = n * (z * p1 - p2) / (z * z - 1.0);
            z1 = z;
            z = z1 - p1 / pp;
            if (fabs(z - z1) <= 1e-15) break;
        }
        xi[i] = 0.5 * (1.0 - z);
        xi[n - 1 - i] = 0.5 * (1.0 + z);
        w[i] = w[n - 1 - i] = 1.0 / ((1.0 - z * z) * pp * pp);
    }
}

/* Largest eigenvalue of the symmetric n x n S (destroyed), by cyclic Jacobi rotations. */
static double largest_eigenvalue(int n, double S[MAX_Q][MAX_Q]) {
    int sweep, p, r, k;
    double largest;
    for (sweep = 0; sweep < 60; sweep++) {
        double off = 0.0, diag = 0.0;
        for (p = 0; p < n; p++) {
            diag += S[p][p] * S[p][p];
            for (r = p + 1; r < n; r++) off += S[p][r] * S[p][r];
        }
        if (off <= 1e-30 * diag) break;
        for (p = 0; p < n; p++)
            for (r = p + 1; r < n; r++) {
                double theta, t, c, sn;
                if (S[p][r] == 0.0) continue;
                theta = (S[r][r] - S[p][p]) / (2.0 * S[p][r]);
                t = (theta >= 0.0 ? 1.0 : -1.0) / (fabs(theta) + sqrt(theta * theta + 1.0));
                c = 1.0 / sqrt(t * t + 1.0);
                sn = t * c;
                for (k = 0; k < n; k++) { /* columns p, r */
                    const double skp = S[k][p], skr = S[k][r];
                    S[k][p] = c * skp - sn * skr;
                    S[k][r] = sn * skp + c * skr;
                }
                for (k = 0; k < n; k++) { /* rows p, r */
                    const double spk = S[p][k], srk = S[r][k];
                    S[p][k] = c * spk - sn * srk;
                    S[r][k] = sn * spk + c * srk;
                }
            }
    }
    largest = S[0][0];
    for (p = 1; p < n; p++)
        if (S[p][p] > largest) largest = S[p][p];
    return largest;
}

/* Largest eigenvalue of M^-1 diag(a), as that of X diag(a) X^T with X = Lc^-1. */
static double largest_ratio(int n, const double Lc[MAX_Q][MAX_Q], const double a[]) {
    double X[MAX_Q][MAX_Q], S[MAX_Q][MAX_Q];
    int i, j, k;
    for (j = 0; j < n; j++) { /* column j of Lc^-1 by forward substitution */
        for (i = 0; i < n; i++) {
            double sum = i == j ? 1.0 : 0.0;
            for (k = 0; k < i; k++) sum -= Lc[i][k] * X[k][j];
            X[i][j] = sum / Lc[i][i];
        }
    }
    for (i = 0; i < n; i++)
        for (j = 0; j < n; j++) {
            double sum = 0.0;
            for (k = 0; k < n; k++) sum += X[i][k] * a[k] * X[j][k];
            S[i][j] = sum;
        }
    return largest_eigenvalue(n, S);
}

/* The substep beyond which RK4 diverges [s] (0 if M is singular). The linearised arm,
 * M q'' + D q' + K q = 0, has modes lambda with |lambda| <= max(rho(M^-1 D), sqrt(rho(M^-1 K)))
 * (each mode's Rayleigh quotients m, d, k give m lambda^2 + d lambda + k = 0); K is bounded by
 * the bending stiffness, the gas's (2 p_max G_a^2 / V_min, the largest compression) and
 * gravity's (|g| x outer mass x outer length), at the straight and the initial configuration.
 * RK4 is stable while |h lambda| <= RK4_RADIUS. */
static double stability_limit(const State *s, const double q_start[]) {
    const int n = s->n_q, nd = s->n_dof;
    const double g_norm = sqrt(s->g[0] * s->g[0] + s->g[1] * s->g[1] + s->g[2] * s->g[2]);
    double damping[MAX_Q], stiffness[MAX_Q], zero[MAX_Q], worst = 0.0;
    int i, j, which;
    for (j = 0; j < n; j++) zero[j] = 0.0;
    for (i = 0; i < s->n_seg; i++) {
        const GasCircuit *c = &s->circuit[i];
        double outer_mass = 0.0, outer_length = 0.0, k_gas = 0.0;
        int o, k;
        for (o = i; o < s->n_seg; o++) {
            outer_length += s->L[o] + 2.0 * s->Lp[o];
            outer_mass += s->m_end[o];
            for (k = 0; k < s->n_nodes; k++) outer_mass += s->m_node[o][k];
        }
        if (s->gas) {
            const double V_min = c->V_dead + c->V_ch0 - c->G_a * s->theta_max;
            const double V_max = gas_base_volume(c, c->stroke) + c->G_a * s->theta_max;
            k_gas = 2.0 * (c->p_atm * V_max / V_min) * c->G_a * c->G_a / V_min;
        }
        for (j = 0; j < nd; j++) {
            damping[i * nd + j] = s->d[i];
            stiffness[i * nd + j] = s->k[i] + k_gas + g_norm * outer_mass * outer_length;
        }
    }
    for (which = 0; which < 2; which++) {
        Dynamics dyn;
        double Lc[MAX_Q][MAX_Q], rho_d, rho_k, rate;
        arm_dynamics(s, which == 0 ? zero : q_start, zero, &dyn);
        if (!cholesky(n, (const double(*)[MAX_Q])dyn.M, Lc)) return 0.0;
        rho_d = largest_ratio(n, (const double(*)[MAX_Q])Lc, damping);
        rho_k = largest_ratio(n, (const double(*)[MAX_Q])Lc, stiffness);
        rate = rho_d > sqrt(rho_k) ? rho_d : sqrt(rho_k);
        if (rate > worst) worst = rate;
    }
    return worst > 0.0 ? RK4_RADIUS / worst : INFINITY;
}

/* Taylor coefficients in W of a = sum (-W)^j / (2j+1)!, b = sum (-W)^j / (2j+2)!,
 * c = sum (-W)^j / (2j+3)!, and of their derivatives: term j of f' is (j+1) f_(j+1), of f''
 * (j+1)(j+2) f_(j+2). */
static void series_coefficients(State *s) {
    double factorial[2 * N_TERMS + 8], f[3][N_TERMS + 2];
    int j, k;
    factorial[0] = 1.0;
    for (j = 1; j < 2 * N_TERMS + 8; j++) factorial[j] = factorial[j - 1] * j;
    for (j = 0; j < N_TERMS + 2; j++)
        for (k = 0; k < 3; k++)
            f[k][j] = (j % 2 == 0 ? 1.0 : -1.0) / factorial[2 * j + 1 + k];
    for (j = 0; j < N_TERMS; j++) {
        for (k = 0; k < 3; k++) {
            s->series[j][3 * k] = f[k][j];
            s->series[j][3 * k + 1] = (j + 1.0) * f[k][j + 1];
            if (k < 2) s->series[j][3 * k + 2] = (j + 1.0) * (j + 2.0) * f[k][j + 2];
        }
    }
}

static GasCircuit circuit_of_segment(const Instance *inst, int i) {
    GasCircuit c;
    c.area = 0.25 * PI * V(inst, bore) * V(inst, bore);
    c.stroke = V(inst, stroke);
    c.V_dead = V(inst, V_dead);
    c.V_ch0 = V(inst, V_ch0);
    c.C_a = V(inst, C_a);
    c.G_a = SEG(inst, G_a, i);
    c.vacuum_factor = V(inst, vacuum_factor);
    c.p_collapse = V(inst, p_collapse);
    c.p_atm = V(inst, p_atm);
    c.R_gas = V(inst, R_gas);
    c.n_poly = 1.0;
    return c;
}

fmi2Status model_initialize(Instance *inst, OdeSystem *ode) {
    State *s = (State *)inst->state;
    double weight[MAX_NODES], q_start[MAX_Q], limit, substep;
    int i, j, k;
    memset(s, 0, sizeof *s);
    s->n_seg = (int)V(inst, n_segments);
    s->n_dof = V(inst, planar) != 0.0 ? 1 : 2;
    s->n_q = s->n_seg * s->n_dof;
    s->n_nodes = (int)V(inst, n_nodes);
    s->gas = V(inst, gas) != 0.0;
    s->theta_max = V(inst, theta_max);
    s->T_gas = V(inst, T_gas);
    s->g[0] = V(inst, g_x);
    s->g[1] = V(inst, g_y);
    s->g[2] = V(inst, g_z);
    series_coefficients(s);
    gauss_legendre(s->n_nodes, s->xi, weight);
    if (V(inst, x_seal) > V(inst, stroke)) {
        log_message(inst, fmi2Error, "invalid parameter x_seal = %g: outside the stroke [0, %g]",
                    V(inst, x_seal), V(inst, stroke));
        return fmi2Error;
    }
    for (i = 0; i < s->n_seg; i++) {
        const double u0 = SEG(inst, theta_x_start, i), v0 = SEG(inst, theta_y_start, i);
        s->L[i] = SEG(inst, L, i);
        s->Lp[i] = SEG(inst, L_p, i);
        s->k[i] = SEG(inst, k, i);
        s->d[i] = SEG(inst, d, i);
        s->m_end[i] = SEG(inst, m_end, i);
        for (k = 0; k < s->n_nodes; k++) s->m_node[i][k] = SEG(inst, mass, i) * weight[k];
        s->circuit[i] = circuit_of_segment(inst, i);
        if (s->n_dof == 1 && v0 != 0.0) {
            log_message(inst, fmi2Error,
                        "invalid parameter theta_y_start_%d = %g: a planar arm bends in x only",
                        i + 1, v0);
            return fmi2Error;
        }
        if (sqrt(u0 * u0 + v0 * v0) > s->theta_max) {
            log_message(inst, fmi2Error,
                        "invalid parameters theta_x_start_%d, theta_y_start_%d: a bend of %g rad "
                        "is beyond theta_max = %g",
                        i + 1, i + 1, sqrt(u0 * u0 + v0 * v0), s->theta_max);
            return fmi2Error;
        }
        q_start[i * s->n_dof] = u0;
        if (s->n_dof == 2) q_start[i * s->n_dof + 1] = v0;
        if (s->gas) {
            const GasCircuit *c = &s->circuit[i];
            const double V_min = c->V_dead + c->V_ch0 - c->G_a * s->theta_max;
            if (!(V_min > 0.0)) {
                log_message(inst, fmi2Error,
                            "invalid parameters: a gas volume of segment %d can reach zero (V_dead "
                            "+ V_ch0 - G_a_%d theta_max = %g m^3 must be positive)",
                            i + 1, i + 1, V_min);
                return fmi2Error;
            }
            /* one gas state per volume: d((p_atm + g) V(g))/dg = V + p (C_a + sign theta dG/dg)
             * stays positive; dG/dg is nonzero only under vacuum, where p < p_atm */
            if (c->p_atm *
                    (c->G_a * (1.0 - c->vacuum_factor) * s->theta_max / c->p_collapse - c->C_a) >=
                V_min) {
                log_message(inst, fmi2Error,
                            "invalid parameters: p_collapse = %g Pa is too sharp for G_a_%d, "
                            "vacuum_factor and theta_max (the channel volume would not be "
                            "monotone in pressure)",
                            c->p_collapse, i + 1);
                return fmi2Error;
            }
        }
    }
    /* every circuit is sealed at atmospheric pressure and T_gas, unbent, piston at x_seal */
    for (k = 0; k < 2; k++) {
        s->V_seal[k] =
            gas_base_volume(&s->circuit[0], gas_swept_length(&s->circuit[0], V(inst, x_seal), k));
        s->gas_mass[k] = V(inst, p_atm) * s->V_seal[k] / (V(inst, R_gas) * s->T_gas);
    }
    limit = stability_limit(s, q_start);
    if (!(limit > 0.0)) {
        log_message(inst, fmi2Error, "invalid parameters: the mass matrix is singular (a segment "
                                     "without mass, or every mass beyond it zero)");
        return fmi2Error;
    }
    substep = V(inst, substep);
    if (substep == 0.0) substep = limit < SUBSTEP_AUTO_MAX ? limit : SUBSTEP_AUTO_MAX; /* automatic */
    if (substep > limit) {
        log_message(inst, fmi2Error,
                    "invalid parameter substep = %g: beyond the stability limit %g s of the arm's "
                    "fastest mode (inertia, damping, bending, gas and gravity stiffness)",
                    substep, limit);
        return fmi2Error;
    }
    for (j = 0; j < s->n_q; j++) s->y[j] = q_start[j];
    for (j = 0; j < s->n_q; j++) {
        const int i_seg = j / s->n_dof, axis = j % s->n_dof;
        s->x[i_seg][axis] = V(inst, x_seal);
        if (s->gas && !applied_piston_position(inst, s, j, &s->x[i_seg][axis])) return fmi2Error;
    }
    stop_at_limit(s); /* a segment starting on its limit rests there */
    s->E_limit = s->W_limit = 0.0;
    ode->n = (size_t)(2 * s->n_q + 3);
    ode->y = s->y;
    ode->nb = 0;
    ode->stability_limit = limit;
    ode->max_substep = substep;
    return model_outputs(inst);
}
