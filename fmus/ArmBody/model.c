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
#define N_TERMS 12         /* series terms: the last one kept is below 2e-18 for W < 1 */
#define SERIES_BELOW 1.0   /* W = (bend angle)^2 below which a, b, c take their series */
#define PISTON_TOLERANCE 1e-9
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
    double series[3][N_TERMS];              /* Taylor coefficients of a, b, c in W */
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

/* sum_j coef[j] W^j and its first two derivatives, by Horner. */
static void series_sum(const double coef[N_TERMS], double W, double out[3]) {
    double f0 = 0.0, f1 = 0.0, f2 = 0.0;
    int j;
    for (j = N_TERMS - 1; j >= 0; j--) {
        f0 = f0 * W + coef[j];
        if (j >= 1) f1 = f1 * W + j * coef[j];
        if (j >= 2) f2 = f2 * W + j * (j - 1) * coef[j];
    }
    out[0] = f0;
    out[1] = f1;
    out[2] = f2;
}

static void bend_functions(const State *s, double W, Bend *f) {
    if (W < SERIES_BELOW) {
        double c[3];
        series_sum(s->series[0], W, f->a);
        series_sum(s->series[1], W, f->b);
        series_sum(s->series[2], W, c);
        f->c[0] = c[0];
        f->c[1] = c[1];
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

/* The arm at (q, q'): M, f, the tips and the gravitational energy. A walk from the base carries
 * each segment's base frame (R, p), its angular velocity Om, the velocity-product parts of its
 * angular and linear accelerations (al, A) and its Jacobians (JO angular, JV linear, 3 x n_q). */
static void arm_dynamics(const State *s, const double q[], const double qd[], Dynamics *out) {
    double R[3][3] = {{1.0, 0.0, 0.0}, {0.0, 1.0, 0.0}, {0.0, 0.0, 1.0}};
    double p[3] = {0.0, 0.0, 0.0}, Om[3] = {0.0, 0.0, 0.0}, al[3] = {0.0, 0.0, 0.0};
    double A[3] = {0.0, 0.0, 0.0};
    double JO[3][MAX_Q], JV[3][MAX_Q], J[3][MAX_Q];
    const int nd = s->n_dof, nq = s->n_q;
    int i, j, l, k, e;
    memset(out, 0, sizeof *out);
    memset(JO, 0, sizeof JO);
    memset(JV, 0, sizeof JV);
    for (i = 0; i < s->n_seg; i++) {
        const int c0 = i * nd, cn = c0 + nd;
        const double u = q[c0], v = nd == 2 ? q[c0 + 1] : 0.0;
        const double ud = qd[c0], vd = nd == 2 ? qd[c0 + 1] : 0.0;
        const double T = u * u + v * v, Td = 2.0 * (u * ud + v * vd);
        const double S = 2.0 * (ud * ud + vd * vd);
        const double L = s->L[i], Lp = s->Lp[i];
        double tip_p[3] = {0.0, 0.0, 0.0}, tip_A[3] = {0.0, 0.0, 0.0};
        double tip_J[3][MAX_Q];
        Bend tipf;
        for (k = 0; k <= s->n_nodes; k++) {
            /* node k of the arc, or the tip frame's origin (k == n_nodes) */
            double F[3], G[3], m;
            double r[3], dr[2][3], rd[3], rdd[3], rho[3], t1[3], t2[3], t3[3], acc[3], gmacc[3];
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
                m = s->m_node[i][k];
            } else {
                bend_functions(s, T, &tipf);
                F[0] = L * tipf.b[0] + Lp * tipf.a[0];
                F[1] = L * tipf.b[1] + Lp * tipf.a[1];
                F[2] = L * tipf.b[2] + Lp * tipf.a[2];
                G[0] = 2.0 * Lp + L * tipf.a[0] - Lp * T * tipf.b[0];
                G[1] = L * tipf.a[1] - Lp * (tipf.b[0] + T * tipf.b[1]);
                G[2] = L * tipf.a[2] - Lp * (2.0 * tipf.b[1] + T * tipf.b[2]);
                m = s->m_end[i];
            }
            /* local position, its derivatives in u and v (dT/du = 2u), velocity and
             * velocity-product acceleration */
            r[0] = F[0] * u;
            r[1] = F[0] * v;
            r[2] = G[0];
            dr[0][0] = 2.0 * u * F[1] * u + F[0];
            dr[0][1] = 2.0 * u * F[1] * v;
            dr[0][2] = 2.0 * u * G[1];
            dr[1][0] = 2.0 * v * F[1] * u;
            dr[1][1] = 2.0 * v * F[1] * v + F[0];
            dr[1][2] = 2.0 * v * G[1];
            rd[0] = F[1] * Td * u + F[0] * ud;
            rd[1] = F[1] * Td * v + F[0] * vd;
            rd[2] = G[1] * Td;
            rdd[0] = (F[2] * Td * Td + F[1] * S) * u + 2.0 * F[1] * Td * ud;
            rdd[1] = (F[2] * Td * Td + F[1] * S) * v + 2.0 * F[1] * Td * vd;
            rdd[2] = G[2] * Td * Td + G[1] * S;
            /* to the base frame: a = A + al x rho + Om x (Om x rho) + 2 Om x R r' + R r'' */
            rotate(R, r, rho);
            cross(al, rho, t1);
            cross(Om, rho, t2);
            cross(Om, t2, t3);
            for (e = 0; e < 3; e++) acc[e] = A[e] + t1[e] + t3[e];
            rotate(R, rd, t1);
            cross(Om, t1, t2);
            rotate(R, rdd, t3);
            for (e = 0; e < 3; e++) {
                acc[e] += 2.0 * t2[e] + t3[e];
                gmacc[e] = s->g[e] - acc[e];
            }
            for (j = 0; j < c0; j++) {
                const double w[3] = {JO[0][j], JO[1][j], JO[2][j]};
                cross(w, rho, t1);
                for (e = 0; e < 3; e++) J[e][j] = JV[e][j] + t1[e];
            }
            for (j = 0; j < nd; j++) {
                rotate(R, dr[j], t1);
                for (e = 0; e < 3; e++) J[e][c0 + j] = t1[e];
            }
            if (m != 0.0) {
                for (j = 0; j < cn; j++) {
                    for (l = j; l < cn; l++)
                        out->M[j][l] += m * (J[0][j] * J[0][l] + J[1][j] * J[1][l] +
                                             J[2][j] * J[2][l]);
                    out->f[j] += m * (J[0][j] * gmacc[0] + J[1][j] * gmacc[1] +
                                      J[2][j] * gmacc[2]);
                }
                out->E_gravity -= m * (s->g[0] * (p[0] + rho[0]) + s->g[1] * (p[1] + rho[1]) +
                                       s->g[2] * (p[2] + rho[2]));
            }
            if (k == s->n_nodes) {
                for (e = 0; e < 3; e++) {
                    tip_p[e] = p[e] + rho[e];
                    tip_A[e] = acc[e];
                    for (j = 0; j < cn; j++) tip_J[e][j] = J[e][j];
                }
            }
        }
        /* the next segment's base frame: R_loc = I + a K + b K^2, angular velocity J_l phi' with
         * phi = (-v, u, 0) (columns J_l e_y for u, -J_l e_x for v), and the velocity-product part
         * of its derivative, b' T' (phi x phi') + c' T' phi x (phi x phi') + c phi' x (phi x phi'),
         * with phi x phi' = (0, 0, u v' - v u') */
        {
            const double a = tipf.a[0], b = tipf.b[0], c = tipf.c[0];
            const double w3 = u * vd - v * ud;
            const double Rl[3][3] = {{1.0 - b * u * u, -b * u * v, a * u},
                                     {-b * u * v, 1.0 - b * v * v, a * v},
                                     {-a * u, -a * v, 1.0 - b * T}};
            const double col[2][3] = {{-c * u * v, 1.0 - c * v * v, -b * v},
                                      {-1.0 + c * u * u, c * u * v, b * u}};
            const double al_loc[3] = {tipf.c[1] * Td * w3 * u + c * w3 * ud,
                                      tipf.c[1] * Td * w3 * v + c * w3 * vd,
                                      tipf.b[1] * Td * w3};
            double w_loc[3], Rw[3], t1[3], t2[3], Rn[3][3];
            for (e = 0; e < 3; e++) w_loc[e] = col[0][e] * ud + col[1][e] * vd;
            rotate(R, w_loc, Rw);
            cross(Om, Rw, t1);
            rotate(R, al_loc, t2);
            for (e = 0; e < 3; e++) {
                al[e] += t1[e] + t2[e];
                Om[e] += Rw[e];
            }
            for (j = 0; j < nd; j++) {
                rotate(R, col[j], t1);
                for (e = 0; e < 3; e++) JO[e][c0 + j] = t1[e];
            }
            for (e = 0; e < 3; e++)
                for (l = 0; l < 3; l++)
                    Rn[e][l] = R[e][0] * Rl[0][l] + R[e][1] * Rl[1][l] + R[e][2] * Rl[2][l];
            memcpy(R, Rn, sizeof R);
            for (e = 0; e < 3; e++) {
                p[e] = tip_p[e];
                A[e] = tip_A[e];
                out->tip[i][e] = tip_p[e];
                for (j = 0; j < cn; j++) JV[e][j] = tip_J[e][j];
            }
        }
    }
    for (j = 0; j < nq; j++)
        for (l = 0; l < j; l++) out->M[j][l] = out->M[l][j];
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
 * acc, the free acceleration, is corrected in place; returns the power the reactions absorb,
 * sum lambda n . q_i' [W] (zero to the integrator's accuracy while the segments rest). */
static double limit_reactions(const State *s, const double q[], const double qd[],
                              const double Lc[MAX_Q][MAX_Q], double acc[]) {
    const int nd = s->n_dof, n = s->n_q;
    Contacts c;
    double b[MAX_SEGMENTS] = {0.0}, rate[MAX_SEGMENTS] = {0.0}, lambda[MAX_SEGMENTS], power = 0.0;
    int part[MAX_SEGMENTS] = {0}, a, j;
    find_contacts(s, q, Lc, s->resting, &c);
    if (c.m == 0) return 0.0;
    for (a = 0; a < c.m; a++) {
        const int i = c.seg[a];
        double speed2 = 0.0;
        rate[a] = 0.0;
        for (j = 0; j < nd; j++) {
            rate[a] += c.normal[a][j] * qd[i * nd + j];
            speed2 += qd[i * nd + j] * qd[i * nd + j];
        }
        b[a] = (speed2 - rate[a] * rate[a]) / c.theta[a];
        for (j = 0; j < nd; j++) b[a] += c.normal[a][j] * acc[i * nd + j];
        part[a] = 1;
    }
    contact_reactions(&c, part, b, lambda);
    for (a = 0; a < c.m; a++) {
        for (j = 0; j < n; j++) acc[j] -= lambda[a] * c.Z[a][j];
        power += lambda[a] * rate[a];
    }
    return power;
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
    damping += limit_reactions(s, q, qd, (const double(*)[MAX_Q])Lc, acc);
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
 * c = sum (-W)^j / (2j+3)!. */
static void series_coefficients(State *s) {
    double factorial[2 * N_TERMS + 4];
    int j;
    factorial[0] = 1.0;
    for (j = 1; j < 2 * N_TERMS + 4; j++) factorial[j] = factorial[j - 1] * j;
    for (j = 0; j < N_TERMS; j++) {
        const double sign = j % 2 == 0 ? 1.0 : -1.0;
        s->series[0][j] = sign / factorial[2 * j + 1];
        s->series[1][j] = sign / factorial[2 * j + 2];
        s->series[2][j] = sign / factorial[2 * j + 3];
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
    double weight[MAX_NODES], q_start[MAX_Q], limit;
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
    if (V(inst, substep) > limit) {
        log_message(inst, fmi2Error,
                    "invalid parameter substep = %g: beyond the stability limit %g s of the arm's "
                    "fastest mode (inertia, damping, bending, gas and gravity stiffness)",
                    V(inst, substep), limit);
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
    ode->max_substep = V(inst, substep);
    return model_outputs(inst);
}
