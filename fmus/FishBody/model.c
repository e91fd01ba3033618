/* FishBody physics: the soft robotic fish of PHYSICS.md section 7, a rigid head free in the plane
 * and a tapered bidirectional tail of two constant-curvature (PCC) pieces driven by two gas
 * channels a and b. See FishValve/model.c for why the fish is three FMUs coupled by mass flow:
 * this one integrates each channel's gas mass from mdot_in - mdot_vent (its inputs, held over the
 * step), so the masses balance exactly against the source and the vents.
 *
 * Coordinates. The reference point is the head-tail joint at (x, y); yaw is the heading of the
 * nose. Body-frame velocities nu = (u, v, r, theta_1', theta_2'): surge u, sway v (to the left),
 * yaw rate r and the pieces' bend rates. A tail point at arc length s behind the joint sits at
 * body coordinates (-s, w(s)) with w(s) = sum_j theta_j phi_j(s), phi_j = 0 before piece j,
 * (s - s_{j-1})^2 / (2 L_j) on it and L_j / 2 + (s - s_j) after it (small-angle PCC shape);
 * theta_j > 0 bends the tail tip to the left (+y), and channel a's volume grows with it:
 *   V_a = V_0 + G_1 theta_1 + G_2 theta_2,   V_b = V_0 - G_1 theta_1 - G_2 theta_2,
 * so pressurising a bends the tail left and, by recoil, turns the head left (yaw up).
 *
 * Kinetic energy [derived, linearised in the bend]: T = m_u u^2 / 2 + nu_l' M nu_l / 2 with
 * nu_l = (v, r, theta'), the lateral velocity of a section b(s)' nu_l, b(s) = (1, -s, phi(s)) on
 * the tail and (1, e) at distance e ahead of the joint on the head, and
 *   M = m_head b_c b_c' + I_head e_r e_r' + int (mu_struct + mu_added) b b' ds
 * (b_c at the head's centroid; mu_added = C_a rho pi h^2 / 4 for a section of depth h). M is
 * constant; its bend block holds each piece's PCC inertia mu L^3 / 20 (= m L^2 / 20) and the
 * couplings to sway and yaw. Integrals are sums over N_SAMPLES midpoints per piece. The dynamics
 * are Kirchhoff's equations for the quasi-velocities u, v, r (the body frame turns):
 *   d(m_u u)/dt = X + r P_v,  dP_v/dt = Y - r m_u u,  dP_r/dt = N - u P_v + v m_u u,
 *   dP_theta_j/dt = G_j (g_a - g_b) - k_j theta_j - d_j theta_j' + Q_j,   P = M nu_l,
 * whose gyroscopic terms do no work: d(T + E_elastic)/dt = gas power - dissipation exactly. The
 * markers (nose, end of each piece) use the exact PCC chain, not the linearised shape.
 *
 * Hydrodynamics [estimate]: added mass (in M and m_u = m_head + m_tail + m_added_surge);
 * resistive drag of each section against its sideways velocity, -rho Cd_lateral h |w| w / 2 per
 * length, and in surge -rho Cd_surge S_front |u| u / 2; reactive force at the tail tip after
 * Lighthill (1960): with U = max(u, 0), tip lateral velocity w_t = b(L)' nu_l and the lateral
 * velocity relative to the water w = w_t + U (theta_1 + theta_2) (the tip's slope), the fin of
 * added mass per length m_f = C_a rho pi h_fin^2 / 4 gives the thrust X_f = m_f (w w_t - w^2 / 2)
 * and the lateral force Y_f = -m_f U w at the tip. Their power, u X_f + w_t Y_f =
 * -m_f U w^2 / 2 + (u - U) X_f, is never positive: the energy shed into the wake [derived]. So
 * every hydrodynamic term dissipates, and a tail beat from rest pushes forward (X_f = m_f w_t^2 / 2).
 *
 * Gas [derived]: each channel is an open control volume of ideal gas with internal energy
 * U = p V / (gamma - 1): dm/dt = mdot_in - mdot_vent and
 *   dU/dt = c_p T_in mdot_in - c_p T_out mdot_vent - p dV/dt - m c_v (T - T_wall) / tau_thermal,
 * T_in the supply temperature for inflow (the channel's own for reverse flow), T_out the channel's
 * for outflow: adiabatic filling (a fast fill heats the gas towards gamma T_supply) relaxing to the
 * walls. Volumes as above (rigid walls apart from the bend).
 *
 * Energy (outputs): W_gas = int (g_a dV_a + g_b dV_b) (gauge pressure: the water pushes back with
 * p_atm) is the work the gas does on the tail; W_gas = E_elastic + E_kinetic + E_resistive to the
 * integrator's accuracy, E_resistive = drag + wake + internal damping. This is the split of the
 * thesis's "Elastic and Resistive Components of Work". */
#include <math.h>

#include "glue.h"

#define PI 3.14159265358979323846
#define N_PIECES 2
#define N_LAT (2 + N_PIECES)
#define N_SAMPLES 16 /* midpoints per piece and on the head */
#define N_POINTS ((N_PIECES + 1) * N_SAMPLES)

/* continuous states, in this order in State.y (MAX_STATES = 16 in glue.h allows two pieces) */
enum {
    M_A, U_A, M_B, U_B,       /* channel gas masses [kg] and internal energies [J] */
    TH_1, TH_2,               /* bend angles [rad] */
    NU_V, NU_R, NU_W1, NU_W2, /* sway [m/s], yaw rate [rad/s], bend rates [rad/s] */
    SURGE, POS_X, POS_Y, YAW, /* surge [m/s], joint position [m], heading [rad] */
    W_GAS, E_RES,             /* gas work and dissipation [J] */
    N_STATES
};

typedef struct {
    double y[N_STATES];
    double m_vented;                /* vented mass [kg], exact sum of the held inputs */
    double M[N_LAT][N_LAT];         /* lateral mass matrix */
    double M_inv[N_LAT][N_LAT];     /* its inverse */
    double m_surge;                 /* surge mass incl. added mass [kg] */
    double b[N_POINTS][N_LAT];      /* section velocity maps b(s) at the sample points */
    double drag[N_POINTS];          /* rho Cd h ds / 2 at the sample points [kg/m] */
    double b_tip[N_LAT];            /* b at the tail tip */
} State;

size_t model_state_size(void) { return sizeof(State); }

static double piece_length(const Instance *inst, int j) { return j == 0 ? V(inst, L_1) : V(inst, L_2); }
static double piece_G(const Instance *inst, int j) { return j == 0 ? V(inst, G_1) : V(inst, G_2); }
static double piece_k(const Instance *inst, int j) { return j == 0 ? V(inst, k_1) : V(inst, k_2); }
static double piece_d(const Instance *inst, int j) { return j == 0 ? V(inst, d_1) : V(inst, d_2); }

static double tail_length(const Instance *inst) { return V(inst, L_1) + V(inst, L_2); }

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

/* Lateral displacement per bend angle of piece j at arc length s: the small-angle PCC shape. */
static double shape(const Instance *inst, int j, double s) {
    double start = 0.0;
    int i;
    const double L = piece_length(inst, j);
    for (i = 0; i < j; i++) start += piece_length(inst, i);
    if (s <= start) return 0.0;
    if (s <= start + L) return (s - start) * (s - start) / (2.0 * L);
    return L / 2.0 + (s - start - L);
}

static void tail_map(const Instance *inst, double s, double b[N_LAT]) {
    int j;
    b[0] = 1.0;
    b[1] = -s;
    for (j = 0; j < N_PIECES; j++) b[2 + j] = shape(inst, j, s);
}

static void add_outer(double M[N_LAT][N_LAT], const double b[N_LAT], double weight) {
    int i, k;
    for (i = 0; i < N_LAT; i++)
        for (k = 0; k < N_LAT; k++) M[i][k] += weight * b[i] * b[k];
}

/* Inverts the symmetric positive definite A by Gauss-Jordan with partial pivoting; 0 if singular. */
static int invert(const double A[N_LAT][N_LAT], double out[N_LAT][N_LAT]) {
    double a[N_LAT][2 * N_LAT];
    int i, k, c;
    for (i = 0; i < N_LAT; i++)
        for (k = 0; k < 2 * N_LAT; k++) a[i][k] = k < N_LAT ? A[i][k] : (k - N_LAT == i);
    for (c = 0; c < N_LAT; c++) {
        int pivot = c;
        for (i = c + 1; i < N_LAT; i++)
            if (fabs(a[i][c]) > fabs(a[pivot][c])) pivot = i;
        if (!(fabs(a[pivot][c]) > 1e-300)) return 0;
        if (pivot != c)
            for (k = 0; k < 2 * N_LAT; k++) {
                const double t = a[c][k];
                a[c][k] = a[pivot][k];
                a[pivot][k] = t;
            }
        {
            const double inv = 1.0 / a[c][c];
            for (k = 0; k < 2 * N_LAT; k++) a[c][k] *= inv;
        }
        for (i = 0; i < N_LAT; i++) {
            const double f = a[i][c];
            if (i == c || f == 0.0) continue;
            for (k = 0; k < 2 * N_LAT; k++) a[i][k] -= f * a[c][k];
        }
    }
    for (i = 0; i < N_LAT; i++)
        for (k = 0; k < N_LAT; k++) out[i][k] = a[i][N_LAT + k];
    return 1;
}

/* Mass matrix, surge mass and the sample points' maps and drag weights. */
static int assemble(Instance *inst) {
    State *s = (State *)inst->state;
    const double L = tail_length(inst), L_head = V(inst, L_head);
    const double half_rho_cd = 0.5 * V(inst, rho_water) * V(inst, Cd_lateral);
    double depth_integral = 0.0, b_c[N_LAT] = {0};
    int i, k, p = 0;
    for (i = 0; i < N_LAT; i++)
        for (k = 0; k < N_LAT; k++) s->M[i][k] = 0.0;
    b_c[0] = 1.0;
    b_c[1] = V(inst, d_head);
    add_outer(s->M, b_c, V(inst, m_head));
    s->M[1][1] += V(inst, I_head);
    /* the head: added mass and drag of sections ahead of the joint */
    for (k = 0; k < N_SAMPLES; k++, p++) {
        const double ds = L_head / N_SAMPLES, e = (k + 0.5) * ds;
        for (i = 0; i < N_LAT; i++) s->b[p][i] = 0.0;
        s->b[p][0] = 1.0;
        s->b[p][1] = e;
        add_outer(s->M, s->b[p], added_mass_per_length(inst, V(inst, h_head)) * ds);
        s->drag[p] = half_rho_cd * V(inst, h_head) * ds;
    }
    /* the tail's structural mass follows its depth: mu = m_tail h(s) / int h ds */
    depth_integral = 0.5 * (V(inst, h_root) + V(inst, h_tip)) * L;
    {
        double start = 0.0;
        int j;
        for (j = 0; j < N_PIECES; j++) {
            const double Lj = piece_length(inst, j), ds = Lj / N_SAMPLES;
            for (k = 0; k < N_SAMPLES; k++, p++) {
                const double sk = start + (k + 0.5) * ds, h = tail_depth(inst, sk);
                const double wet = wetted_depth(inst, sk);
                const double mu_struct = depth_integral > 0.0 ? V(inst, m_tail) * h / depth_integral
                                                              : V(inst, m_tail) / L;
                tail_map(inst, sk, s->b[p]);
                add_outer(s->M, s->b[p], (mu_struct + added_mass_per_length(inst, wet)) * ds);
                s->drag[p] = half_rho_cd * wet * ds;
            }
            start += Lj;
        }
    }
    tail_map(inst, L, s->b_tip);
    s->m_surge = V(inst, m_head) + V(inst, m_tail) + V(inst, m_added_surge);
    return invert((const double(*)[N_LAT])s->M, s->M_inv);
}

/* Channel volumes [m^3] at bend angles theta. */
static void channel_volumes(const Instance *inst, const double y[], double vol[2]) {
    const double bend = V(inst, G_1) * y[TH_1] + V(inst, G_2) * y[TH_2];
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

static double dot(const double a[N_LAT], const double b[N_LAT]) {
    double sum = 0.0;
    int i;
    for (i = 0; i < N_LAT; i++) sum += a[i] * b[i];
    return sum;
}

/* A piece resting against its mechanical limit and pushed further is held there: a constraint
 * force lambda on its bend coordinate, M nu' = F + sum lambda_j e_j with theta_j'' = 0, solved
 * exactly on the constant mass matrix (at most two pieces). It does no work (theta_j' = 0), so the
 * energy balance holds; the stop itself is the projection in model_after_substep. */
static void stop_at_limits(const Instance *inst, const double y[], const double F[N_LAT],
                           double acc[N_LAT]) {
    const State *s = (const State *)inst->state;
    const double limit = V(inst, theta_max);
    int active[N_PIECES], n = 0, j, i;
    (void)F;
    for (j = 0; j < N_PIECES; j++) {
        const double th = y[TH_1 + j], rate = y[NU_W1 + j], a = acc[2 + j];
        if ((th >= limit && rate >= 0.0 && a > 0.0) || (th <= -limit && rate <= 0.0 && a < 0.0))
            active[n++] = 2 + j;
    }
    if (n == 1) {
        const int c = active[0];
        const double lambda = -acc[c] / s->M_inv[c][c];
        for (i = 0; i < N_LAT; i++) acc[i] += lambda * s->M_inv[i][c];
    } else if (n == 2) {
        const int c0 = active[0], c1 = active[1];
        const double a = s->M_inv[c0][c0], b = s->M_inv[c0][c1], c = s->M_inv[c1][c0],
                     d = s->M_inv[c1][c1], det = a * d - b * c;
        const double l0 = (-acc[c0] * d + acc[c1] * b) / det;
        const double l1 = (-acc[c1] * a + acc[c0] * c) / det;
        for (i = 0; i < N_LAT; i++) acc[i] += l0 * s->M_inv[i][c0] + l1 * s->M_inv[i][c1];
    }
}

int model_derivatives(const Instance *inst, const double y[], double dy[]) {
    const State *s = (const State *)inst->state;
    const double gamma = V(inst, gamma), R = V(inst, R_gas);
    const double cv = R / (gamma - 1.0), cp = gamma * cv;
    const double *nu = &y[NU_V], u = y[SURGE];
    const double m_fin = added_mass_per_length(inst, V(inst, h_fin));
    double Q[N_LAT] = {0}, P[N_LAT], Pdot[N_LAT], X, power_res = 0.0, bend_rate = 0.0;
    Channels c;
    int i, k, side;
    if (!channel_state(inst, y, &c)) return 0;
    /* gas */
    for (i = 0; i < N_PIECES; i++) bend_rate += piece_G(inst, i) * nu[2 + i];
    for (side = 0; side < 2; side++) {
        const double in = side == 0 ? V(inst, mdot_in_a) : V(inst, mdot_in_b);
        const double out = side == 0 ? V(inst, mdot_vent_a) : V(inst, mdot_vent_b);
        const double T = c.T[side], T_in = in >= 0.0 ? V(inst, T_supply) : T;
        const double T_out = out >= 0.0 ? T : V(inst, T_supply);
        const double vol_rate = side == 0 ? bend_rate : -bend_rate;
        const double p = c.g[side] + V(inst, p_atm), m = y[M_A + 2 * side];
        dy[M_A + 2 * side] = in - out;
        dy[U_A + 2 * side] = cp * T_in * in - cp * T_out * out - p * vol_rate -
                             m * cv * (T - V(inst, T_wall)) / V(inst, tau_thermal);
    }
    dy[W_GAS] = (c.g[0] - c.g[1]) * bend_rate;
    /* actuation, elasticity and internal damping on the bend coordinates */
    for (i = 0; i < N_PIECES; i++) {
        const double rate = nu[2 + i];
        Q[2 + i] += piece_G(inst, i) * (c.g[0] - c.g[1]) - piece_k(inst, i) * y[TH_1 + i] -
                    piece_d(inst, i) * rate;
        power_res += piece_d(inst, i) * rate * rate;
    }
    /* resistive drag of every section */
    for (k = 0; k < N_POINTS; k++) {
        const double w = dot(s->b[k], nu), f = -s->drag[k] * fabs(w) * w;
        for (i = 0; i < N_LAT; i++) Q[i] += f * s->b[k][i];
        power_res -= f * w;
    }
    /* surge drag and the reactive force at the tail tip (Lighthill) */
    {
        const double U = u > 0.0 ? u : 0.0, w_t = dot(s->b_tip, nu);
        const double w = w_t + U * (y[TH_1] + y[TH_2]);
        const double thrust = m_fin * (w * w_t - 0.5 * w * w), lateral = -m_fin * U * w;
        const double surge_drag = 0.5 * V(inst, rho_water) * V(inst, Cd_surge) * V(inst, S_front);
        X = thrust - surge_drag * fabs(u) * u;
        for (i = 0; i < N_LAT; i++) Q[i] += lateral * s->b_tip[i];
        power_res += surge_drag * fabs(u) * u * u - (u * thrust + w_t * lateral);
    }
    dy[E_RES] = power_res;
    /* Kirchhoff's equations */
    for (i = 0; i < N_LAT; i++) P[i] = dot(s->M[i], nu);
    {
        const double P_u = s->m_surge * u, v = nu[0], r = nu[1];
        dy[SURGE] = (X + r * P[0]) / s->m_surge;
        Pdot[0] = Q[0] - r * P_u;
        Pdot[1] = Q[1] - u * P[0] + v * P_u;
        for (i = 2; i < N_LAT; i++) Pdot[i] = Q[i];
        for (i = 0; i < N_LAT; i++) dy[NU_V + i] = dot(s->M_inv[i], Pdot);
        stop_at_limits(inst, y, Pdot, &dy[NU_V]);
        dy[POS_X] = u * cos(y[YAW]) - v * sin(y[YAW]);
        dy[POS_Y] = u * sin(y[YAW]) + v * cos(y[YAW]);
        dy[YAW] = r;
    }
    for (i = 0; i < N_PIECES; i++) dy[TH_1 + i] = nu[2 + i];
    return 1;
}

double model_time_to_event(const Instance *inst) {
    (void)inst;
    return INFINITY;
}

void model_discrete_update(Instance *inst) { (void)inst; }

static double elastic_energy(const Instance *inst, const double y[]);
static double kinetic_energy(const State *s);

/* The vented mass is the held input integrated exactly (no solver rounding beyond the sum). A
 * piece past its mechanical limit theta_max is put back on it and stopped (an inelastic stop);
 * the gas does g dV on the volume change and whatever the stop removes from the elastic and
 * kinetic energy is counted as dissipated, so the energy balance stays exact. */
void model_after_substep(Instance *inst, double dt) {
    State *s = (State *)inst->state;
    double *y = s->y;
    const double limit = V(inst, theta_max);
    int j, hit = 0;
    s->m_vented += (V(inst, mdot_vent_a) + V(inst, mdot_vent_b)) * dt;
    for (j = 0; j < N_PIECES; j++) hit |= fabs(y[TH_1 + j]) > limit;
    if (hit) {
        Channels c;
        double before = elastic_energy(inst, y) + kinetic_energy(s), vol_before[2], vol_after[2];
        double gas_work;
        channel_volumes(inst, y, vol_before);
        if (!channel_state(inst, y, &c)) return; /* model_outputs reports it */
        for (j = 0; j < N_PIECES; j++) {
            const double th = y[TH_1 + j];
            if (fabs(th) <= limit) continue;
            y[TH_1 + j] = th > 0.0 ? limit : -limit;
            if (y[NU_W1 + j] * th > 0.0) y[NU_W1 + j] = 0.0;
        }
        channel_volumes(inst, y, vol_after);
        gas_work = c.g[0] * (vol_after[0] - vol_before[0]) + c.g[1] * (vol_after[1] - vol_before[1]);
        y[W_GAS] += gas_work;
        y[E_RES] += gas_work + before - elastic_energy(inst, y) - kinetic_energy(s);
    }
}

fmi2Status model_step_start(Instance *inst) {
    (void)inst;
    return fmi2OK;
}

static double elastic_energy(const Instance *inst, const double y[]) {
    double e = 0.0;
    int j;
    for (j = 0; j < N_PIECES; j++) e += 0.5 * piece_k(inst, j) * y[TH_1 + j] * y[TH_1 + j];
    return e;
}

static double kinetic_energy(const State *s) {
    const double *nu = &s->y[NU_V];
    double e = 0.5 * s->m_surge * s->y[SURGE] * s->y[SURGE];
    int i;
    for (i = 0; i < N_LAT; i++) e += 0.5 * nu[i] * dot(s->M[i], nu);
    return e;
}

/* sin(z) / z, exact near 0. */
static double sinc(double z) { return fabs(z) < 1e-4 ? 1.0 - z * z / 6.0 : sin(z) / z; }

fmi2Status model_outputs(Instance *inst) {
    State *s = (State *)inst->state;
    const double *y = s->y;
    const double yaw = y[YAW], u = y[SURGE], v = y[NU_V], r = y[NU_R], d = V(inst, d_head);
    double dy[N_STATES], px = y[POS_X], py = y[POS_Y], direction = yaw + PI;
    Channels c;
    int j;
    if (!channel_state(inst, y, &c) || !model_derivatives(inst, y, dy)) {
        log_message(inst, fmi2Error,
                    "no physical channel state (masses %g, %g kg; bend angles %g, %g rad): a gas "
                    "mass or volume reached zero",
                    y[M_A], y[M_B], y[TH_1], y[TH_2]);
        return fmi2Error;
    }
    V(inst, x) = px;
    V(inst, y) = py;
    V(inst, yaw) = yaw;
    V(inst, x_dot) = dy[POS_X];
    V(inst, y_dot) = dy[POS_Y];
    V(inst, yaw_rate) = r;
    V(inst, surge) = u;
    V(inst, sway) = v;
    {
        /* the head's centroid sits at (d, 0) in the turning body frame */
        const double ax = dy[SURGE] - r * (v + d * r), ay = dy[NU_V] + d * dy[NU_R] + r * u;
        V(inst, a_head_x) = ax * cos(yaw) - ay * sin(yaw);
        V(inst, a_head_y) = ax * sin(yaw) + ay * cos(yaw);
        V(inst, a_head) = hypot(ax, ay);
    }
    V(inst, theta_1) = y[TH_1];
    V(inst, theta_2) = y[TH_2];
    V(inst, kappa_1) = y[TH_1] / V(inst, L_1);
    V(inst, kappa_2) = y[TH_2] / V(inst, L_2);
    V(inst, nose_x) = px + V(inst, L_head) * cos(yaw);
    V(inst, nose_y) = py + V(inst, L_head) * sin(yaw);
    /* exact PCC chain backwards from the joint: a positive bend turns the tail to the left,
     * i.e. clockwise while walking from the joint towards the tip */
    for (j = 0; j < N_PIECES; j++) {
        const double turn = -y[TH_1 + j], L = piece_length(inst, j);
        const double chord = L * sinc(0.5 * turn);
        px += chord * cos(direction + 0.5 * turn);
        py += chord * sin(direction + 0.5 * turn);
        direction += turn;
        if (j == 0) {
            V(inst, tail_1_x) = px;
            V(inst, tail_1_y) = py;
        } else {
            V(inst, tail_2_x) = px;
            V(inst, tail_2_y) = py;
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
    V(inst, m_vented) = s->m_vented;
    V(inst, W_gas) = y[W_GAS];
    V(inst, E_elastic) = elastic_energy(inst, y);
    V(inst, E_kinetic) = kinetic_energy(s);
    V(inst, E_resistive) = y[E_RES];
    return fmi2OK;
}

/* The substep beyond which RK4 diverges on the tail's modes [s]: 2.5 / rate with the rate bounded
 * by sqrt(trace(M^-1 K)) + trace(M^-1 D) (M^-1 K is similar to a positive semidefinite matrix,
 * so its largest eigenvalue is at most its trace), K the bending stiffness plus the gas stiffness
 * gamma p G_j^2 (1 / V_a + 1 / V_b) at up to ten atmospheres in channels down to half V_0. */
static double tail_stability_limit(const Instance *inst) {
    const State *s = (const State *)inst->state;
    const double p_max = 10.0 * V(inst, p_atm), V_min = 0.5 * V(inst, V_0);
    double stiffness = 0.0, damping = 0.0;
    int j;
    for (j = 0; j < N_PIECES; j++) {
        const double G = piece_G(inst, j);
        const double k = piece_k(inst, j) + V(inst, gamma) * p_max * G * G * 2.0 / V_min;
        stiffness += s->M_inv[2 + j][2 + j] * k;
        damping += s->M_inv[2 + j][2 + j] * piece_d(inst, j);
    }
    return 2.5 / (sqrt(stiffness) + damping);
}

fmi2Status model_initialize(Instance *inst, OdeSystem *ode) {
    State *s = (State *)inst->state;
    const double p_atm = V(inst, p_atm), V0 = V(inst, V_0);
    int side, j;
    if (!assemble(inst)) {
        log_message(inst, fmi2Error, "invalid parameters: the mass matrix is singular (no mass?)");
        return fmi2Error;
    }
    ode->stability_limit = tail_stability_limit(inst);
    if (V(inst, substep) > ode->stability_limit) {
        log_message(inst, fmi2Error,
                    "invalid parameter substep = %g: beyond the stability limit %g s of the tail "
                    "modes (inertia, stiffness, gas stiffness and damping)",
                    V(inst, substep), ode->stability_limit);
        return fmi2Error;
    }
    if (!(V0 - (V(inst, G_1) + V(inst, G_2)) * V(inst, theta_max) >= 0.25 * V0)) {
        log_message(inst, fmi2Error,
                    "invalid parameters: at theta_max = %g rad the compressed channel keeps less "
                    "than a quarter of V_0 = %g m^3 (reduce G_1, G_2 or theta_max)",
                    V(inst, theta_max), V0);
        return fmi2Error;
    }
    for (j = 0; j < N_STATES; j++) s->y[j] = 0.0;
    /* both channels start straight, at ambient pressure and wall temperature */
    for (side = 0; side < 2; side++) {
        s->y[M_A + 2 * side] = p_atm * V0 / (V(inst, R_gas) * V(inst, T_wall));
        s->y[U_A + 2 * side] = p_atm * V0 / (V(inst, gamma) - 1.0);
    }
    s->y[POS_X] = V(inst, x_start);
    s->y[POS_Y] = V(inst, y_start);
    s->y[YAW] = V(inst, yaw_start);
    s->m_vented = 0.0;
    ode->n = N_STATES;
    ode->y = s->y;
    ode->max_substep = V(inst, substep);
    return model_outputs(inst);
}
