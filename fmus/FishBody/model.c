/* FishBody physics: the thesis's soft robotic fish, a rigid head free in the plane
 * and a tapered bidirectional tail of three constant-curvature (PCC) pieces driven by two gas
 * channels a and b, as a planar multibody chain valid at any bend. Each channel is fed by its
 * valve's supply nozzle and drained by its vent; the valves publish the nozzles' effective areas
 * (FishValve/model.c says why) and this model integrates the flows through them together with the
 * channels' gas, in its own substeps. It publishes the mass each channel drew from the supply over
 * the last step (mdot_in_a, mdot_in_b, step means) for GasSource, which takes it off the canister
 * over the next step. Invariants: canister + channels + vented - drawn back = the initial gas to
 * rounding, counting the step's draw not yet taken off the canister (mdot_in h); W_gas =
 * E_elastic + E_kinetic + E_resistive to the integrator's accuracy, and every hydrodynamic term
 * dissipates or is conservative.
 *
 * Coordinates q = (X, Y, psi, theta_1, theta_2, theta_3): the head-tail joint at (X, Y) in the
 * world, the heading psi of the nose and the pieces' bend angles. Walking from the joint to the
 * tip the backbone's direction is phi(s) = psi + pi - B_{j-1} - theta_j (s - s_{j-1}) / L_j on
 * piece j (B_j = theta_1 + ... + theta_j), so theta_j > 0 bends the tail tip to the left (+y of
 * the head) and channel a's volume grows with it:
 *   V_a = V_0 + sum G_j theta_j,   V_b = V_0 - sum G_j theta_j,
 * so pressurising a bends the tail left and, by recoil, turns the head left (yaw up).
 * Positions are the exact PCC chain (as controllers/kinematics.py) in complex form: a point at
 * local arc sigma on piece j sits at
 *   r = X + i Y + sum_m l_m sinc(a_m / 2) exp(i (psi + pi - B_{m-1} - a_m / 2))
 * over the pieces m <= j, a_m = theta_m for a whole piece (l_m = L_m) and theta_j
 * sigma / L_j for the partial one (l_j = sigma). Its Jacobian J = dr/dq and the velocity-product
 * acceleration J' q' follow in closed form from each term (see `chain_term`), exact at every bend
 * (series of sinc and its derivatives near zero).
 *
 * Mechanics [derived]: Lagrange's equations of T = 1/2 q'^T M(q) q' with
 *   M = m_head J_c^T J_c + I_head e_psi e_psi^T + sum_k mu_k ds J_k^T J_k
 *       + sum_k ma_k ds (J_k^T n_k)(n_k^T J_k) + m_added_surge (J_c^T t_c)(t_c^T J_c)
 * over sample points k (N_SAMPLES midpoints per piece and N_HEAD_SAMPLES on the head): the
 * head's centroid c at d_head ahead of the joint, the tail's structural mass mu (following its
 * depth) and the added mass of each slender section, ma = C_a rho pi h^2 / 4 per length, acting
 * on the velocity normal to the section, w = n . v. For a mass m acting on the velocity along a
 * direction d(phi) turning with the section (e = dd/dphi, phi' = a . q'), w = b . q' with
 * b = J^T d, and Lagrange's equations give
 *   m b (b . q'' + d . (J' q') + phi' e . v) + m w (phi' J^T e - (e . v) a)
 * (the second bracket holds the Munk moment); for the full velocity (structural mass) it is
 * m J^T (J q'' + J' q'). These inertial forces do no net work, so the kinetic energy changes only
 * by the generalised forces: the gas, elasticity, damping and water resistance.
 *
 * Hydrodynamics [estimate]: added mass as above; resistive-force theory per section: normal drag
 * -rho Cd_lateral h |w| w / 2 and tangential skin friction -rho Cf_tangential h |u_t| u_t per
 * length (wetted perimeter 2 h), u_t = t . v; form drag of the head in surge
 * -rho Cd_surge S_front |u| u / 2; the reactive force of the caudal fin at the tip after
 * Lighthill's large-amplitude elongated-body theory (1971): with m_f = C_a rho pi h_fin^2 / 4,
 * tip tangent t (towards the tip), w = n . v_tip and U = max(-t . v_tip, 0) the water streaming
 * off the trailing edge, F_tip = m_f (-w^2 t / 2 - U w n): thrust from a tail beat even from rest,
 * and a power F_tip . v_tip = -m_f U w^2 / 2 (or -m_f w^2 (t . v) / 2 when U = 0), never
 * positive: the energy shed into the wake. Drag on every section of the head and the tail resists
 * yaw, so a fish that has turned comes to rest in yaw (no free spinning).
 *
 * Escape turn [definition, as biologists measure a C-start]: stage 1 is the contraction that
 * bends the body into a C; it ends when the head's yaw rate first returns to zero. The heading
 * change is the head's yaw change from rest to the end of stage 1 and the turn time its duration
 * (from the onset of the head's rotation); the peak yaw rate and the peak acceleration of the
 * head's centroid are taken over the manoeuvre. The tests compute them from yaw, yaw_rate and
 * a_head.
 *
 * Gas [derived]: each channel is an open control volume of ideal gas with internal energy
 * U = p V / (gamma - 1): dm/dt = mdot_in - mdot_vent and
 *   dU/dt = c_p T_in mdot_in - c_p T_out mdot_vent - p dV/dt - m c_v (T - T_wall) / tau_thermal,
 * T_in the supply temperature for inflow (the channel's own for reverse flow), T_out the channel's
 * for outflow (ambient gas at T_wall drawn back through the vent): adiabatic filling (a fast fill
 * heats the gas towards gamma T_supply) relaxing to the walls. Volumes as above (rigid walls apart
 * from the bend); the bending torque on piece j is G_j (p_a - p_b) (virtual work of the gas).
 *
 * Nozzle flow of an ideal gas from upstream (p_u, T_u) to downstream p_d, r = p_d / p_u, effective
 * area CdA (isentropic flow to the throat, Saint-Venant-Wantzel) [derived]:
 *   choked,   r <= r_c: mdot = CdA p_u sqrt(gamma / (R T_u)) (2 / (gamma + 1))^((gamma+1)/(2(gamma-1)))
 *   subsonic, r >  r_c: mdot = CdA p_u sqrt(2 gamma / ((gamma - 1) R T_u) (r^(2/gamma) - r^((gamma+1)/gamma)))
 * with r_c = (2 / (gamma + 1))^(gamma / (gamma - 1)) = 0.5475 for CO2; the two branches meet with
 * a continuous slope at r_c, and a reverse pressure drop reverses the flow (upstream swapped).
 * mdot_in_j runs from the supply (p_supply, T_supply) to channel j, mdot_vent_j from channel j to
 * ambient (p_atm, T_wall).
 *
 * Stiffness of the gas, and its stability limit [derived]: near equal pressures the flow behaves
 * as CdA sqrt(2 rho dp), whose slope is unbounded, so a channel settles on its supply or on
 * ambient with a time constant that tends to zero; no explicit substep resolves that exactly. So
 * within dp_lin of equal pressures the flow is taken as mdot (3 - x) sqrt(x) / 2, x = dp / dp_lin
 * (linear in dp at zero, equal to the law with the same slope at dp_lin), and dp_lin is set at the
 * start of each step, per nozzle, so that the linearised rate of the channel there, K slope with
 * K = gamma R T / V the channel's pressure per mass and slope = 1.5 CdA sqrt(2 rho / dp_lin), is
 * one per substep: dp_lin = 4.5 rho (K CdA h)^2. RK4's amplification on a real rate is positive
 * up to its stability limit 2.79 / h (its value at h lambda = 1 is 0.375, at 2 (two nozzles of a
 * channel open at once, mid-travel) 0.33), so a channel approaches its supply or ambient
 * monotonically, never beyond it, and a vented channel does not oscillate. Where dp_lin would
 * exceed 1 % of the larger pressure (a large nozzle, a compressed hot channel) the substep is
 * split into up to 8 parts, which divides dp_lin by up to 64. The only error is the approach
 * within dp_lin (at most about 1 % of the pressure) of equilibrium: exponential with the substep's
 * time constant where the square-root law would arrive in a finite time of the same order. The
 * supply and the vent are ideal pressure sources over a step (the regulator holds the set
 * pressure; ambient is fixed), so the loop that matters, channel and nozzle, is inside this model.
 *
 * Energy (outputs): W_gas = int (g_a dV_a + g_b dV_b) (gauge pressure: the water pushes back with
 * p_atm) is the work the gas does on the tail; W_gas = E_elastic + E_kinetic + E_resistive to the
 * integrator's accuracy, E_resistive = drag + wake + internal damping + mechanical stops. This is
 * the split of the thesis's "Elastic and Resistive Components of Work". */
#include <complex.h>
#include <math.h>

#include "glue.h"

#define PI 3.14159265358979323846
#define N_PIECES 3
#define N_Q (3 + N_PIECES)  /* X, Y, psi, theta_1..theta_N */
#define N_SAMPLES 10        /* midpoints per tail piece */
#define N_HEAD_SAMPLES 8    /* midpoints on the head */
#define N_POINTS (N_HEAD_SAMPLES + N_PIECES * N_SAMPLES)
#define SMALL_ANGLE 0.1     /* below it sinc and its derivatives take their series */
#define LINEAR_BAND 0.01    /* dp_lin at most this share of the larger pressure, by splitting */
#define MAX_SPLIT 8         /* the glue's MAX_PARTS */

/* continuous states, in this order in State.y (at most MAX_STATES, glue.h) */
enum {
    M_A, U_A, M_B, U_B,                    /* channel gas masses [kg] and internal energies [J] */
    Q_X, Q_Y, Q_PSI, Q_TH,                 /* joint [m], heading [rad], bend angles [rad] ... */
    DQ_X = Q_X + N_Q, DQ_Y, DQ_PSI, DQ_TH, /* ... and their rates [m/s], [rad/s] */
    W_GAS = DQ_X + N_Q, E_RES,             /* gas work and dissipation [J] */
    SUPPLIED_A, SUPPLIED_B,                /* mass drawn from the supply per channel [kg] */
    VENTED, RETURNED,                      /* mass out through the vents and drawn back [kg] */
    N_STATES
};

/* A sample point of the backbone: on the head at `offset` ahead of the joint (piece < 0), or on
 * tail piece `piece` at the fraction `fraction` of its length. */
typedef struct {
    int piece;
    double offset, fraction;
    double mass;     /* structural mass [kg] */
    double added;    /* added mass normal to the section [kg] */
    double c_normal; /* rho Cd_lateral h ds / 2 [kg/m] */
    double c_tangent; /* rho Cf_tangential h ds [kg/m] (both faces) */
} Point;

typedef struct {
    double y[N_STATES];
    Point points[N_POINTS];
    double dp_lin[2][2];        /* per channel: the nozzle's and the vent's linear band [Pa] */
    int parts;                  /* into how many parts this step's substeps are split */
    double step_elapsed;        /* time integrated since the last step's start [s] */
    double supplied_start[2];   /* SUPPLIED_A, SUPPLIED_B then */
} State;

/* Kinematics of one material point at (q, q'): position, Jacobian, velocity, velocity-product
 * acceleration J' q', tangent angle phi and its gradient a = dphi/dq (constant). */
typedef struct {
    double complex r, J[N_Q], v, acc_vp;
    double phi, phi_rate, a[N_Q];
    int n;                  /* J and a are zero from index n on (the pieces beyond the point's) */
    double complex tangent; /* exp(i phi) */
} Kinematics;

size_t model_state_size(void) { return sizeof(State); }

static double piece_length(const Instance *inst, int j) {
    return j == 0 ? V(inst, L_1) : j == 1 ? V(inst, L_2) : V(inst, L_3);
}
static double piece_G(const Instance *inst, int j) {
    return j == 0 ? V(inst, G_1) : j == 1 ? V(inst, G_2) : V(inst, G_3);
}
static double piece_k(const Instance *inst, int j) {
    return j == 0 ? V(inst, k_1) : j == 1 ? V(inst, k_2) : V(inst, k_3);
}
static double piece_d(const Instance *inst, int j) {
    return j == 0 ? V(inst, d_1) : j == 1 ? V(inst, d_2) : V(inst, d_3);
}

static double tail_length(const Instance *inst) {
    double L = 0.0;
    int j;
    for (j = 0; j < N_PIECES; j++) L += piece_length(inst, j);
    return L;
}

/* Depth of the tail's body at arc length s behind the joint [m] (linear taper). */
static double tail_depth(const Instance *inst, double s) {
    return V(inst, h_root) + (V(inst, h_tip) - V(inst, h_root)) * s / tail_length(inst);
}

/* Depth the water sees at arc length s [m]: the body, or the caudal fin over the last L_fin. */
static double wetted_depth(const Instance *inst, double s) {
    const double h = tail_depth(inst, s);
    if (s >= tail_length(inst) - V(inst, L_fin) && V(inst, h_fin) > h) return V(inst, h_fin);
    return h;
}

/* Added mass per length of a section of depth h [kg/m]. */
static double added_mass_per_length(const Instance *inst, double h) {
    return V(inst, C_a) * V(inst, rho_water) * PI * h * h / 4.0;
}

/* sinc(x) = sin(x) / x and its first two derivatives, series below SMALL_ANGLE (next terms
 * x^10 / 11!, which is below rounding there). */
static void sinc_derivatives(double x, double out[3]) {
    const double x2 = x * x;
    if (fabs(x) < SMALL_ANGLE) {
        out[0] = 1.0 - x2 / 6.0 * (1.0 - x2 / 20.0 * (1.0 - x2 / 42.0 * (1.0 - x2 / 72.0)));
        out[1] = x * (-1.0 / 3.0 + x2 * (1.0 / 30.0 + x2 * (-1.0 / 840.0 + x2 / 45360.0)));
        out[2] = -1.0 / 3.0 + x2 * (1.0 / 10.0 + x2 * (-1.0 / 168.0 + x2 / 6480.0));
        return;
    }
    {
        const double s = sin(x), c = cos(x);
        out[0] = s / x;
        out[1] = (x * c - s) / x2;
        out[2] = ((2.0 - x2) * s - 2.0 * x * c) / (x2 * x);
    }
}

/* Adds one chord of the PCC chain to k: length l sinc(a / 2) along Phi = psi + pi - B - a / 2,
 * a = f theta_m, B the bend of the pieces before m. With c(a) = l sinc(a / 2):
 *   dr = (c' da + i c dPhi) E,  J' q' = (c'' a'^2 + 2 i c' a' Phi' - c Phi'^2) E,  E = exp(i Phi). */
static void chain_term(const double q[], const double dq[], int m, double l, double f,
                       Kinematics *k) {
    double bend = 0.0, bend_rate = 0.0, sd[3];
    int i;
    for (i = 0; i < m; i++) {
        bend += q[3 + i];
        bend_rate += dq[3 + i];
    }
    {
        const double a = f * q[3 + m], a_rate = f * dq[3 + m];
        const double Phi = q[2] + PI - bend - 0.5 * a, Phi_rate = dq[2] - bend_rate - 0.5 * a_rate;
        const double complex E = cexp(I * Phi);
        double c, c1, c2;
        sinc_derivatives(0.5 * a, sd);
        c = l * sd[0];
        c1 = 0.5 * l * sd[1];
        c2 = 0.25 * l * sd[2];
        k->r += c * E;
        k->J[2] += I * c * E;
        for (i = 0; i < m; i++) k->J[3 + i] -= I * c * E;
        k->J[3 + m] += f * (c1 - 0.5 * I * c) * E;
        k->v += (c1 * a_rate + I * c * Phi_rate) * E;
        k->acc_vp += (c2 * a_rate * a_rate + 2.0 * I * c1 * a_rate * Phi_rate -
                      c * Phi_rate * Phi_rate) * E;
    }
}

/* The tail chain at the joint, before any piece's chord. */
static void tail_base(const double q[], const double dq[], Kinematics *k) {
    int i;
    for (i = 0; i < N_Q; i++) {
        k->J[i] = 0.0;
        k->a[i] = 0.0;
    }
    k->r = q[0] + I * q[1];
    k->J[0] = 1.0;
    k->J[1] = I;
    k->v = dq[0] + I * dq[1];
    k->acc_vp = 0.0;
}

/* The point on tail piece j at the fraction f of its length, from k holding the chain through
 * the pieces before j. */
static void tail_finish(const Instance *inst, const double q[], const double dq[], int j, double f,
                        Kinematics *k) {
    int i;
    chain_term(q, dq, j, f * piece_length(inst, j), f, k);
    k->a[2] = 1.0;
    k->phi = q[2] + PI - f * q[3 + j];
    k->phi_rate = dq[2] - f * dq[3 + j];
    for (i = 0; i < j; i++) {
        k->a[3 + i] = -1.0;
        k->phi -= q[3 + i];
        k->phi_rate -= dq[3 + i];
    }
    k->a[3 + j] = -f;
    k->n = 4 + j;
    k->tangent = cexp(I * k->phi);
}

/* Kinematics of a point on tail piece j at the fraction f of its length. */
static void tail_point(const Instance *inst, const double q[], const double dq[], int j, double f,
                       Kinematics *k) {
    int i;
    tail_base(q, dq, k);
    for (i = 0; i < j; i++) chain_term(q, dq, i, piece_length(inst, i), 1.0, k);
    tail_finish(inst, q, dq, j, f, k);
}

/* Kinematics of a point of the rigid head at `offset` ahead of the joint (tangent: the heading). */
static void head_point(const double q[], const double dq[], double offset, Kinematics *k) {
    const double complex E = cexp(I * q[2]);
    int i;
    for (i = 0; i < N_Q; i++) {
        k->J[i] = 0.0;
        k->a[i] = 0.0;
    }
    k->r = q[0] + I * q[1] + offset * E;
    k->J[0] = 1.0;
    k->J[1] = I;
    k->J[2] = I * offset * E;
    k->v = dq[0] + I * dq[1] + I * offset * dq[2] * E;
    k->acc_vp = -offset * dq[2] * dq[2] * E;
    k->phi = q[2];
    k->phi_rate = dq[2];
    k->a[2] = 1.0;
    k->n = 3;
    k->tangent = E; /* exp(i phi), phi = q[2]: the same call */
}

/* Real dot product of two plane vectors written as complex numbers: the real part of conj(a) b
 * (a_r b_r - (-a_i) b_i, the same double), without the imaginary part and the NaN recovery of a
 * C99 complex product. */
static double vdot(double complex a, double complex b) {
    return creal(a) * creal(b) + cimag(a) * cimag(b);
}

/* The mass-matrix terms below skip the coordinates a point does not move with (J and a zero
 * from k->n on: their terms add zeros, which leave a finite sum as it is) and, unless `full`, the
 * upper triangle, which the Cholesky factor never reads; the entries they add to are the same
 * sums in the same order, bit for bit. */

/* Adds the inertia of a full point mass m: M += m J^T J, h += m J^T (J' q'). */
static void add_point_mass(const Kinematics *k, double m, double M[N_Q][N_Q], double h[N_Q],
                           int full) {
    int i, l;
    for (i = 0; i < k->n; i++) {
        for (l = 0; l < (full ? k->n : i + 1); l++) M[i][l] += m * vdot(k->J[i], k->J[l]);
        h[i] += m * vdot(k->J[i], k->acc_vp);
    }
}

/* Adds the inertia of a mass m acting on the velocity along the direction d (turning with the
 * point's tangent, e = dd/dphi): see the header. */
static void add_projected_mass(const Kinematics *k, double complex d, double complex e, double m,
                               double M[N_Q][N_Q], double h[N_Q], int full) {
    double b[N_Q], je[N_Q];
    const double w = vdot(d, k->v), ev = vdot(e, k->v);
    const double bdot_q = vdot(d, k->acc_vp) + k->phi_rate * ev;
    int i, l;
    for (i = 0; i < k->n; i++) {
        b[i] = vdot(d, k->J[i]);
        je[i] = vdot(e, k->J[i]);
    }
    for (i = 0; i < k->n; i++) {
        for (l = 0; l < (full ? k->n : i + 1); l++) M[i][l] += m * b[i] * b[l];
        h[i] += m * (b[i] * bdot_q + w * (k->phi_rate * je[i] - ev * k->a[i]));
    }
}

/* Adds a force F [N] acting at the point to the generalised forces Q. */
static void add_force(const Kinematics *k, double complex F, double Q[N_Q]) {
    int i;
    for (i = 0; i < N_Q; i++) Q[i] += vdot(k->J[i], F);
}

/* The kinematics of the head's centroid and of every sample point at (q, q'), computed once
 * for the inertia and the forces of a state. */
typedef struct {
    Kinematics head, points[N_POINTS];
} Sections;

static void sections(const Instance *inst, const double q[], const double dq[], Sections *k) {
    const State *s = (const State *)inst->state;
    Kinematics chain[N_PIECES]; /* chain[j]: the tail chain through pieces 0 .. j - 1 */
    int p, j;
    head_point(q, dq, V(inst, d_head), &k->head);
    tail_base(q, dq, &chain[0]);
    for (j = 1; j < N_PIECES; j++) {
        chain[j] = chain[j - 1];
        chain_term(q, dq, j - 1, piece_length(inst, j - 1), 1.0, &chain[j]);
    }
    for (p = 0; p < N_POINTS; p++) {
        const Point *pt = &s->points[p];
        if (pt->piece < 0) {
            head_point(q, dq, pt->offset, &k->points[p]);
        } else {
            k->points[p] = chain[pt->piece];
            tail_finish(inst, q, dq, pt->piece, pt->fraction, &k->points[p]);
        }
    }
}

/* Mass matrix M(q) (its lower triangle only unless `full`; the rest is zero) and the
 * velocity-product forces h(q, q') of body, tail and entrained water. */
static void inertia(const Instance *inst, const Sections *k, double M[N_Q][N_Q], double h[N_Q],
                    int full) {
    const State *s = (const State *)inst->state;
    int i, l, p;
    for (i = 0; i < N_Q; i++) {
        h[i] = 0.0;
        for (l = 0; l < N_Q; l++) M[i][l] = 0.0;
    }
    add_point_mass(&k->head, V(inst, m_head), M, h, full);
    M[2][2] += V(inst, I_head);
    {
        const double complex t = k->head.tangent;
        add_projected_mass(&k->head, t, I * t, V(inst, m_added_surge), M, h, full);
    }
    for (p = 0; p < N_POINTS; p++) {
        const Point *pt = &s->points[p];
        const Kinematics *kp = &k->points[p];
        const double complex tan = kp->tangent, n = I * tan;
        if (pt->mass > 0.0) add_point_mass(kp, pt->mass, M, h, full);
        add_projected_mass(kp, n, -tan, pt->added, M, h, full);
    }
}

/* The whole mass matrix and h at (q, q'). */
static void full_inertia(const Instance *inst, const double q[], const double dq[],
                         double M[N_Q][N_Q], double h[N_Q]) {
    Sections k;
    sections(inst, q, dq, &k);
    inertia(inst, &k, M, h, 1);
}

/* Cholesky factor of the symmetric positive definite A (lower triangle in L); 0 if not SPD. */
static int cholesky(const double A[N_Q][N_Q], double L[N_Q][N_Q]) {
    int i, j, k;
    for (i = 0; i < N_Q; i++)
        for (j = 0; j <= i; j++) {
            double sum = A[i][j];
            for (k = 0; k < j; k++) sum -= L[i][k] * L[j][k];
            if (i == j) {
                if (!(sum > 0.0)) return 0;
                L[i][i] = sqrt(sum);
            } else {
                L[i][j] = sum / L[j][j];
            }
        }
    return 1;
}

/* Solves L L^T x = b in place. */
static void cholesky_solve(const double L[N_Q][N_Q], double x[N_Q]) {
    int i, k;
    for (i = 0; i < N_Q; i++) {
        for (k = 0; k < i; k++) x[i] -= L[i][k] * x[k];
        x[i] /= L[i][i];
    }
    for (i = N_Q - 1; i >= 0; i--) {
        for (k = i + 1; k < N_Q; k++) x[i] -= L[k][i] * x[k];
        x[i] /= L[i][i];
    }
}

static double critical_ratio(double gamma) {
    return pow(2.0 / (gamma + 1.0), gamma / (gamma - 1.0));
}

/* Mass flow [kg/s] through a nozzle of effective area CdA from upstream (p_u, T_u) to p_d <= p_u,
 * choked or subsonic (see the header). */
static double forward_flow(double CdA, double p_u, double T_u, double p_d, double gamma, double R) {
    const double r = p_d / p_u;
    if (!(p_u > 0.0) || CdA == 0.0) return 0.0;
    if (r <= critical_ratio(gamma)) {
        return CdA * p_u * sqrt(gamma / (R * T_u)) *
               pow(2.0 / (gamma + 1.0), (gamma + 1.0) / (2.0 * (gamma - 1.0)));
    }
    {
        const double bracket = pow(r, 2.0 / gamma) - pow(r, (gamma + 1.0) / gamma);
        return CdA * p_u * sqrt(2.0 * gamma / ((gamma - 1.0) * R * T_u) * (bracket > 0.0 ? bracket : 0.0));
    }
}

/* Signed mass flow from side 1 to side 2 [kg/s], the higher pressure upstream, linear within
 * dp_lin of equal pressures (see the header). */
static double nozzle_flow(double CdA, double p1, double T1, double p2, double T2, double gamma,
                          double R, double dp_lin) {
    const double dp = fabs(p1 - p2);
    double q = p1 >= p2 ? forward_flow(CdA, p1, T1, p2, gamma, R)
                        : -forward_flow(CdA, p2, T2, p1, gamma, R);
    if (dp < dp_lin) {
        const double x = dp / dp_lin;
        q *= 0.5 * (3.0 - x) * sqrt(x);
    }
    return q;
}

/* Channel volumes [m^3] at bend angles theta. */
static void channel_volumes(const Instance *inst, const double y[], double vol[2]) {
    double bend = 0.0;
    int j;
    for (j = 0; j < N_PIECES; j++) bend += piece_G(inst, j) * y[Q_TH + j];
    vol[0] = V(inst, V_0) + bend;
    vol[1] = V(inst, V_0) - bend;
}

typedef struct {
    double g[2];     /* gauge pressures [Pa] */
    double T[2];     /* temperatures [K] */
    double vol[2];   /* volumes [m^3] */
} Channels;

static int channel_state(const Instance *inst, const double y[], Channels *c) {
    const double gm1 = V(inst, gamma) - 1.0, cv = V(inst, R_gas) / gm1;
    int side;
    channel_volumes(inst, y, c->vol);
    for (side = 0; side < 2; side++) {
        const double m = y[M_A + 2 * side], U = y[U_A + 2 * side];
        if (!(m > 0.0) || !(U > 0.0) || !(c->vol[side] > 0.0)) return 0;
        c->g[side] = gm1 * U / c->vol[side] - V(inst, p_atm);
        c->T[side] = U / (m * cv);
    }
    return 1;
}

/* A piece resting against its mechanical limit and pushed further is held there: constraint
 * forces lambda on the bend coordinates of the active set A, M q'' = F + sum lambda_c e_c with
 * theta_c'' = 0, i.e. (M^-1)_AA lambda = -q''_A. They do no work (theta_c' = 0), so the energy
 * balance holds; the stop itself is the projection in model_after_substep. */
static void stop_at_limits(const Instance *inst, const double y[], const double L[N_Q][N_Q],
                           double acc[N_Q]) {
    const double limit = V(inst, theta_max);
    double cols[N_PIECES][N_Q], A[N_PIECES][N_PIECES + 1];
    int active[N_PIECES], n = 0, j, i, r;
    for (j = 0; j < N_PIECES; j++) {
        const double th = y[Q_TH + j], rate = y[DQ_TH + j], a = acc[3 + j];
        if ((th >= limit && rate >= 0.0 && a > 0.0) || (th <= -limit && rate <= 0.0 && a < 0.0))
            active[n++] = 3 + j;
    }
    if (n == 0) return;
    for (j = 0; j < n; j++) {
        for (i = 0; i < N_Q; i++) cols[j][i] = i == active[j];
        cholesky_solve(L, cols[j]);
    }
    /* the small SPD system by Gaussian elimination without pivoting */
    for (r = 0; r < n; r++) {
        for (j = 0; j < n; j++) A[r][j] = cols[j][active[r]];
        A[r][n] = -acc[active[r]];
    }
    for (r = 0; r < n; r++)
        for (i = r + 1; i < n; i++) {
            const double f = A[i][r] / A[r][r];
            for (j = r; j <= n; j++) A[i][j] -= f * A[r][j];
        }
    for (r = n - 1; r >= 0; r--) {
        double lambda = A[r][n];
        for (j = r + 1; j < n; j++) lambda -= A[r][j] * A[j][n];
        A[r][n] = lambda / A[r][r];
    }
    for (j = 0; j < n; j++)
        for (i = 0; i < N_Q; i++) acc[i] += A[j][n] * cols[j][i];
}

/* Generalised forces of gas, elasticity, damping and water on q, and the power they dissipate. */
static double generalised_forces(const Instance *inst, const double y[], const Channels *c,
                                 const Sections *sec, double Q[N_Q]) {
    const State *s = (const State *)inst->state;
    const double *q = &y[Q_X], *dq = &y[DQ_X];
    double power_res = 0.0;
    Kinematics k;
    int i, p;
    for (i = 0; i < N_Q; i++) Q[i] = 0.0;
    /* actuation, elasticity and internal damping on the bend coordinates */
    for (i = 0; i < N_PIECES; i++) {
        const double rate = dq[3 + i];
        Q[3 + i] += piece_G(inst, i) * (c->g[0] - c->g[1]) - piece_k(inst, i) * q[3 + i] -
                    piece_d(inst, i) * rate;
        power_res += piece_d(inst, i) * rate * rate;
    }
    /* resistive-force theory on every section */
    for (p = 0; p < N_POINTS; p++) {
        const Point *pt = &s->points[p];
        const Kinematics *kp = &sec->points[p];
        const double complex t = kp->tangent, n = I * t;
        const double w = vdot(n, kp->v), u_t = vdot(t, kp->v);
        const double complex F =
            -pt->c_normal * fabs(w) * w * n - pt->c_tangent * fabs(u_t) * u_t * t;
        add_force(kp, F, Q);
        power_res -= vdot(F, kp->v);
    }
    /* form drag of the head in surge, at its centroid */
    {
        const double c_surge = 0.5 * V(inst, rho_water) * V(inst, Cd_surge) * V(inst, S_front);
        const double complex t = sec->head.tangent;
        const double u = vdot(t, sec->head.v);
        const double complex F = -c_surge * fabs(u) * u * t;
        add_force(&sec->head, F, Q);
        power_res -= vdot(F, sec->head.v);
    }
    /* the reactive force of the caudal fin at the trailing edge (Lighthill 1971) */
    {
        const double m_f = added_mass_per_length(inst, V(inst, h_fin));
        tail_point(inst, q, dq, N_PIECES - 1, 1.0, &k);
        {
            const double complex t = cexp(I * k.phi), n = I * t;
            const double w = vdot(n, k.v), stream = -vdot(t, k.v), U = stream > 0.0 ? stream : 0.0;
            const double complex F = m_f * (-0.5 * w * w * t - U * w * n);
            add_force(&k, F, Q);
            power_res -= vdot(F, k.v);
        }
    }
    return power_res;
}

/* Accelerations q'' at the state y; 0 if the mass matrix is singular. */
static int accelerations(const Instance *inst, const double y[], const Sections *sec,
                         const double Q[N_Q], double acc[N_Q]) {
    double M[N_Q][N_Q], L[N_Q][N_Q], h[N_Q];
    int i;
    inertia(inst, sec, M, h, 0);
    if (!cholesky((const double(*)[N_Q])M, L)) return 0;
    for (i = 0; i < N_Q; i++) acc[i] = Q[i] - h[i];
    cholesky_solve((const double(*)[N_Q])L, acc);
    stop_at_limits(inst, y, (const double(*)[N_Q])L, acc);
    return 1;
}

/* The nozzle's and the vent's flows of channel `side` at its absolute pressure p and temperature
 * T [kg/s]: from the supply into the channel, and from the channel to ambient. */
static void flows(const Instance *inst, int side, double p, double T, double *in, double *out) {
    const State *s = (const State *)inst->state;
    const double gamma = V(inst, gamma), R = V(inst, R_gas);
    const double CdA_in = side == 0 ? V(inst, CdA_in_a) : V(inst, CdA_in_b);
    const double CdA_vent = side == 0 ? V(inst, CdA_vent_a) : V(inst, CdA_vent_b);
    *in = nozzle_flow(CdA_in, V(inst, p_supply), V(inst, T_supply), p, T, gamma, R,
                      s->dp_lin[side][0]);
    *out = nozzle_flow(CdA_vent, p, T, V(inst, p_atm), V(inst, T_wall), gamma, R,
                       s->dp_lin[side][1]);
}

int model_derivatives(const Instance *inst, const double y[], double dy[]) {
    const double gamma = V(inst, gamma), R = V(inst, R_gas);
    const double cv = R / (gamma - 1.0), cp = gamma * cv;
    double Q[N_Q], bend_rate = 0.0;
    Channels c;
    Sections sec;
    int i, side;
    if (!channel_state(inst, y, &c)) return 0;
    /* gas */
    for (i = 0; i < N_PIECES; i++) bend_rate += piece_G(inst, i) * y[DQ_TH + i];
    dy[VENTED] = dy[RETURNED] = 0.0;
    for (side = 0; side < 2; side++) {
        const double T = c.T[side], p = c.g[side] + V(inst, p_atm), m = y[M_A + 2 * side];
        const double vol_rate = side == 0 ? bend_rate : -bend_rate;
        double in, out;
        flows(inst, side, p, T, &in, &out);
        dy[SUPPLIED_A + side] = in;
        dy[out >= 0.0 ? VENTED : RETURNED] += fabs(out);
        dy[M_A + 2 * side] = in - out;
        dy[U_A + 2 * side] = cp * (in >= 0.0 ? V(inst, T_supply) : T) * in -
                             cp * (out >= 0.0 ? T : V(inst, T_wall)) * out - p * vol_rate -
                             m * cv * (T - V(inst, T_wall)) / V(inst, tau_thermal);
    }
    dy[W_GAS] = (c.g[0] - c.g[1]) * bend_rate;
    sections(inst, &y[Q_X], &y[DQ_X], &sec);
    dy[E_RES] = generalised_forces(inst, y, &c, &sec, Q);
    for (i = 0; i < N_Q; i++) dy[Q_X + i] = y[DQ_X + i];
    return accelerations(inst, y, &sec, Q, &dy[DQ_X]);
}

double model_time_to_event(const Instance *inst) {
    (void)inst;
    return INFINITY;
}

void model_discrete_update(Instance *inst) { (void)inst; }

static double elastic_energy(const Instance *inst, const double y[]) {
    double e = 0.0;
    int j;
    for (j = 0; j < N_PIECES; j++) e += 0.5 * piece_k(inst, j) * y[Q_TH + j] * y[Q_TH + j];
    return e;
}

static double kinetic_energy(const Instance *inst, const double y[]) {
    double M[N_Q][N_Q], h[N_Q], e = 0.0;
    int i, l;
    full_inertia(inst, &y[Q_X], &y[DQ_X], M, h);
    for (i = 0; i < N_Q; i++)
        for (l = 0; l < N_Q; l++) e += 0.5 * y[DQ_X + i] * M[i][l] * y[DQ_X + l];
    return e;
}

/* A piece past its mechanical limit theta_max is put back on it and stopped (an inelastic stop);
 * the gas does g dV on the volume change and whatever the stop removes from the elastic and
 * kinetic energy is counted as dissipated, so the energy balance stays exact. */
void model_after_substep(Instance *inst, double dt) {
    State *s = (State *)inst->state;
    double *y = s->y;
    const double limit = V(inst, theta_max);
    int j, hit = 0;
    s->step_elapsed += dt;
    for (j = 0; j < N_PIECES; j++) hit |= fabs(y[Q_TH + j]) > limit;
    if (hit) {
        Channels c;
        double before = elastic_energy(inst, y) + kinetic_energy(inst, y), vol_before[2],
               vol_after[2], gas_work;
        channel_volumes(inst, y, vol_before);
        if (!channel_state(inst, y, &c)) return; /* model_outputs reports it */
        for (j = 0; j < N_PIECES; j++) {
            const double th = y[Q_TH + j];
            if (fabs(th) <= limit) continue;
            y[Q_TH + j] = th > 0.0 ? limit : -limit;
            if (y[DQ_TH + j] * th > 0.0) y[DQ_TH + j] = 0.0;
        }
        channel_volumes(inst, y, vol_after);
        gas_work = c.g[0] * (vol_after[0] - vol_before[0]) + c.g[1] * (vol_after[1] - vol_before[1]);
        y[W_GAS] += gas_work;
        y[E_RES] += gas_work + before - elastic_energy(inst, y) - kinetic_energy(inst, y);
    }
}

/* The linear bands dp_lin of the four nozzles for a substep of h / parts at the state y, and the
 * parts (a power of two up to MAX_SPLIT) that keep each within LINEAR_BAND of the larger pressure
 * (see the header); 0 if the channel state is not physical. */
static int linear_bands(Instance *inst, const double y[]) {
    State *s = (State *)inst->state;
    const double gamma = V(inst, gamma), R = V(inst, R_gas), h = V(inst, substep);
    double band[2][2], share = 0.0;
    Channels c;
    int side, k;
    if (!channel_state(inst, y, &c)) return 0;
    for (side = 0; side < 2; side++) {
        const double p = c.g[side] + V(inst, p_atm), T = c.T[side];
        const double ends[2][2] = {{V(inst, p_supply), V(inst, T_supply)},
                                   {V(inst, p_atm), V(inst, T_wall)}};
        const double CdA[2] = {side == 0 ? V(inst, CdA_in_a) : V(inst, CdA_in_b),
                               side == 0 ? V(inst, CdA_vent_a) : V(inst, CdA_vent_b)};
        for (k = 0; k < 2; k++) {
            const double T_max = fmax(T, ends[k][1]);
            const double rho = fmax(p / (R * T), ends[k][0] / (R * ends[k][1]));
            const double K = gamma * R * T_max / c.vol[side];
            const double rate_h = K * CdA[k] * h;
            band[side][k] = 4.5 * rho * rate_h * rate_h;
            share = fmax(share, band[side][k] / (LINEAR_BAND * fmax(p, ends[k][0])));
        }
    }
    s->parts = 1;
    while (s->parts < MAX_SPLIT && share > (double)s->parts * s->parts) s->parts *= 2;
    for (side = 0; side < 2; side++)
        for (k = 0; k < 2; k++) s->dp_lin[side][k] = band[side][k] / (s->parts * s->parts);
    return 1;
}

static int split(const Instance *inst, double h) {
    (void)h;
    return ((const State *)inst->state)->parts;
}

fmi2Status model_step_start(Instance *inst) {
    State *s = (State *)inst->state;
    s->step_elapsed = 0.0;
    s->supplied_start[0] = s->y[SUPPLIED_A];
    s->supplied_start[1] = s->y[SUPPLIED_B];
    if (!linear_bands(inst, s->y)) {
        log_message(inst, fmi2Error, "no physical channel state at t = %g", inst->time);
        return fmi2Error;
    }
    return fmi2OK;
}

fmi2Status model_outputs(Instance *inst) {
    State *s = (State *)inst->state;
    const double *y = s->y, *q = &y[Q_X], *dq = &y[DQ_X];
    const double yaw = q[2];
    const double complex heading = cexp(I * yaw), joint_v = dq[0] + I * dq[1];
    double dy[N_STATES];
    Channels c;
    Kinematics k;
    int j;
    if (!channel_state(inst, y, &c) || !model_derivatives(inst, y, dy)) {
        log_message(inst, fmi2Error,
                    "no physical channel state (masses %g, %g kg; bend angles %g, %g, %g rad): a "
                    "gas mass or volume reached zero or the mass matrix is singular",
                    y[M_A], y[M_B], q[3], q[4], q[5]);
        return fmi2Error;
    }
    V(inst, x) = q[0];
    V(inst, y) = q[1];
    V(inst, yaw) = yaw;
    V(inst, x_dot) = dq[0];
    V(inst, y_dot) = dq[1];
    V(inst, yaw_rate) = dq[2];
    V(inst, surge) = vdot(heading, joint_v);
    V(inst, sway) = vdot(I * heading, joint_v);
    head_point(q, dq, V(inst, d_head), &k);
    {
        double complex a = k.acc_vp;
        int i;
        for (i = 0; i < N_Q; i++) a += k.J[i] * dy[DQ_X + i];
        V(inst, a_head_x) = creal(a);
        V(inst, a_head_y) = cimag(a);
        V(inst, a_head) = cabs(a);
    }
    V(inst, theta_1) = q[3];
    V(inst, theta_2) = q[4];
    V(inst, theta_3) = q[5];
    V(inst, kappa_1) = q[3] / V(inst, L_1);
    V(inst, kappa_2) = q[4] / V(inst, L_2);
    V(inst, kappa_3) = q[5] / V(inst, L_3);
    V(inst, nose_x) = q[0] + V(inst, L_head) * cos(yaw);
    V(inst, nose_y) = q[1] + V(inst, L_head) * sin(yaw);
    for (j = 0; j < N_PIECES; j++) {
        tail_point(inst, q, dq, j, 1.0, &k);
        if (j == 0) {
            V(inst, tail_1_x) = creal(k.r);
            V(inst, tail_1_y) = cimag(k.r);
        } else if (j == 1) {
            V(inst, tail_2_x) = creal(k.r);
            V(inst, tail_2_y) = cimag(k.r);
        } else {
            V(inst, tail_3_x) = creal(k.r);
            V(inst, tail_3_y) = cimag(k.r);
        }
    }
    V(inst, p_a) = c.g[0];
    V(inst, p_b) = c.g[1];
    V(inst, T_a) = c.T[0];
    V(inst, T_b) = c.T[1];
    V(inst, m_a) = y[M_A];
    V(inst, m_b) = y[M_B];
    V(inst, v_a) = c.vol[0];
    V(inst, v_b) = c.vol[1];
    {
        const double dt = s->step_elapsed;
        V(inst, mdot_in_a) = dt > 0.0 ? (y[SUPPLIED_A] - s->supplied_start[0]) / dt : 0.0;
        V(inst, mdot_in_b) = dt > 0.0 ? (y[SUPPLIED_B] - s->supplied_start[1]) / dt : 0.0;
    }
    V(inst, m_vented) = y[VENTED];
    V(inst, m_vent_return) = y[RETURNED];
    V(inst, W_gas) = y[W_GAS];
    V(inst, E_elastic) = elastic_energy(inst, y);
    V(inst, E_kinetic) = kinetic_energy(inst, y);
    V(inst, E_resistive) = y[E_RES];
    return fmi2OK;
}

/* Sample points: midpoints on the head and on each tail piece, with their structural mass (the
 * tail's follows its depth: mu = m_tail h(s) / int h ds), added mass and drag weights. */
static void place_points(Instance *inst) {
    State *s = (State *)inst->state;
    const double L = tail_length(inst), L_head = V(inst, L_head), rho = V(inst, rho_water);
    const double depth_integral = 0.5 * (V(inst, h_root) + V(inst, h_tip)) * L;
    double start = 0.0;
    int j, k, p = 0;
    for (k = 0; k < N_HEAD_SAMPLES; k++, p++) {
        const double ds = L_head / N_HEAD_SAMPLES, h = V(inst, h_head);
        Point *pt = &s->points[p];
        pt->piece = -1;
        pt->offset = (k + 0.5) * ds;
        pt->fraction = 0.0;
        pt->mass = 0.0; /* the head's mass is m_head at d_head, with I_head */
        pt->added = added_mass_per_length(inst, h) * ds;
        pt->c_normal = 0.5 * rho * V(inst, Cd_lateral) * h * ds;
        pt->c_tangent = rho * V(inst, Cf_tangential) * h * ds;
    }
    for (j = 0; j < N_PIECES; j++) {
        const double Lj = piece_length(inst, j), ds = Lj / N_SAMPLES;
        for (k = 0; k < N_SAMPLES; k++, p++) {
            const double sk = start + (k + 0.5) * ds, h = tail_depth(inst, sk);
            const double wet = wetted_depth(inst, sk);
            Point *pt = &s->points[p];
            pt->piece = j;
            pt->offset = 0.0;
            pt->fraction = (k + 0.5) / N_SAMPLES;
            pt->mass = (depth_integral > 0.0 ? V(inst, m_tail) * h / depth_integral
                                             : V(inst, m_tail) / L) * ds;
            pt->added = added_mass_per_length(inst, wet) * ds;
            pt->c_normal = 0.5 * rho * V(inst, Cd_lateral) * wet * ds;
            pt->c_tangent = rho * V(inst, Cf_tangential) * wet * ds;
        }
        start += Lj;
    }
}

/* The substep beyond which RK4 diverges on the tail's modes [s]: 2.5 / rate with the rate bounded
 * by sqrt(trace(M^-1 K)) + trace(M^-1 D) at the straight tail (M^-1 K is similar to a positive
 * semidefinite matrix, so its largest eigenvalue is at most its trace), K the bending stiffness
 * plus the gas stiffness gamma p G_j^2 (1 / V_a + 1 / V_b) at up to ten atmospheres in channels
 * down to half V_0. The bend changes M by a bounded factor; the default substep keeps a margin. */
static double tail_stability_limit(const Instance *inst, int *ok) {
    const double p_max = 10.0 * V(inst, p_atm), V_min = 0.5 * V(inst, V_0);
    double M[N_Q][N_Q], L[N_Q][N_Q], h[N_Q], q[N_Q] = {0}, dq[N_Q] = {0};
    double stiffness = 0.0, damping = 0.0;
    int j;
    full_inertia(inst, q, dq, M, h);
    *ok = cholesky((const double(*)[N_Q])M, L);
    if (!*ok) return 0.0;
    for (j = 0; j < N_PIECES; j++) {
        const double G = piece_G(inst, j);
        const double k = piece_k(inst, j) + V(inst, gamma) * p_max * G * G * 2.0 / V_min;
        double e[N_Q] = {0};
        e[3 + j] = 1.0;
        cholesky_solve((const double(*)[N_Q])L, e); /* column 3 + j of M^-1 */
        stiffness += e[3 + j] * k;
        damping += e[3 + j] * piece_d(inst, j);
    }
    return 2.5 / (sqrt(stiffness) + damping);
}

fmi2Status model_initialize(Instance *inst, OdeSystem *ode) {
    State *s = (State *)inst->state;
    const double p_atm = V(inst, p_atm), V0 = V(inst, V_0);
    double G_sum = 0.0;
    int side, j, ok;
    place_points(inst);
    ode->stability_limit = tail_stability_limit(inst, &ok);
    if (!ok) {
        log_message(inst, fmi2Error, "invalid parameters: the mass matrix is singular (no mass?)");
        return fmi2Error;
    }
    if (V(inst, substep) > ode->stability_limit) {
        log_message(inst, fmi2Error,
                    "invalid parameter substep = %g: beyond the stability limit %g s of the tail "
                    "modes (inertia, stiffness, gas stiffness and damping)",
                    V(inst, substep), ode->stability_limit);
        return fmi2Error;
    }
    for (j = 0; j < N_PIECES; j++) G_sum += piece_G(inst, j);
    if (!(V0 - G_sum * V(inst, theta_max) >= 0.25 * V0)) {
        log_message(inst, fmi2Error,
                    "invalid parameters: at theta_max = %g rad the compressed channel keeps less "
                    "than a quarter of V_0 = %g m^3 (reduce G_1, G_2, G_3 or theta_max)",
                    V(inst, theta_max), V0);
        return fmi2Error;
    }
    for (j = 0; j < N_STATES; j++) s->y[j] = 0.0;
    /* both channels start straight, at ambient pressure and wall temperature */
    for (side = 0; side < 2; side++) {
        s->y[M_A + 2 * side] = p_atm * V0 / (V(inst, R_gas) * V(inst, T_wall));
        s->y[U_A + 2 * side] = p_atm * V0 / (V(inst, gamma) - 1.0);
    }
    s->y[Q_X] = V(inst, x_start);
    s->y[Q_Y] = V(inst, y_start);
    s->y[Q_PSI] = V(inst, yaw_start);
    s->step_elapsed = 0.0;
    s->supplied_start[0] = s->supplied_start[1] = 0.0;
    ode->n = N_STATES;
    ode->y = s->y;
    ode->max_substep = V(inst, substep);
    ode->parts = split;
    if (!linear_bands(inst, s->y)) return fmi2Error; /* not reached: the start is physical */
    return model_outputs(inst);
}
