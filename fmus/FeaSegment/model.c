/* FeaSegment physics (PHYSICS.md section 2): one bidirectional fluidic elastomer segment and the
 * two sealed gas circuits that drive it. Side i in {a, b} is cylinder chamber + tubing + channel:
 *   V_i = A s_i(x) + V_dead + V_ch0 + sign_i G_a theta + C_a g_i,  s_a = stroke - x, s_b = x,
 * with gauge pressure g_i from the gas law p V^n = p_atm (m / rho_atm)^n (n = 1: isothermal,
 * solved in closed form; n > 1: Newton). The bend angle obeys
 *   I theta'' + d theta' + k theta = G_a (g_a - g_b) + tau_ext,  I = m L^2 / 3,
 * clamped to |theta| <= theta_max. Gas masses are states so that a leak can drain them. */
#include <math.h>

#include "glue.h"

#define PI 3.14159265358979323846

typedef struct {
    double theta, omega; /* bend angle [rad] and rate [rad/s] */
    double m_a, m_b;     /* gas mass of each circuit [kg] */
} State;

size_t model_state_size(void) { return sizeof(State); }

static double bore_area(const Instance *inst) {
    return 0.25 * PI * V(inst, bore) * V(inst, bore);
}

static double bending_inertia(const Instance *inst) {
    return V(inst, mass) * V(inst, length) * V(inst, length) / 3.0;
}

static double atmospheric_density(const Instance *inst) {
    return V(inst, p_atm) / (V(inst, R_gas) * V(inst, T_gas));
}

/* Gas volume of one side at zero gauge pressure (the compliance term is added by the solver). */
static double rigid_volume(const Instance *inst, double swept_length, double sign, double theta) {
    return bore_area(inst) * swept_length + V(inst, V_dead) + V(inst, V_ch0) +
           sign * V(inst, G_a) * theta;
}

/* Gauge pressure of a circuit of gas mass m whose volume is V0 + C_a g: solves
 * (p_atm + g) (V0 + C g)^n = p_atm (m / rho_atm)^n for the root with p_atm + g > 0.
 * Returns 0 if no physical root exists (volume collapsed). */
static int gas_pressure(const Instance *inst, double V0, double m, double *gauge) {
    const double p_atm = V(inst, p_atm), C = V(inst, C_a), n = V(inst, n_poly);
    const double v_atm = m / atmospheric_density(inst); /* volume of the gas at p_atm */
    double g;
    int iteration;
    if (!(V0 > 0.0) || !(m > 0.0)) return 0;
    if (n == 1.0) {
        /* C g^2 + (C p_atm + V0) g + (p_atm V0 - p_atm v_atm) = 0, stable form of the + root */
        const double B = C * p_atm + V0, c0 = p_atm * (V0 - v_atm);
        const double disc = B * B - 4.0 * C * c0;
        if (disc < 0.0) return 0;
        *gauge = -2.0 * c0 / (B + sqrt(disc));
        return 1;
    }
    /* Newton on f(g) = ln(p_atm + g) + n ln(V0 + C g) - n ln(v_atm) - ln(p_atm), monotone in g */
    g = p_atm * pow(v_atm / V0, n) - p_atm; /* rigid solution as the starting point */
    for (iteration = 0; iteration < 50; iteration++) {
        const double p = p_atm + g, vol = V0 + C * g;
        double f, df, step;
        if (!(p > 0.0) || !(vol > 0.0)) return 0;
        f = log(p) + n * log(vol) - n * log(v_atm) - log(p_atm);
        df = 1.0 / p + n * C / vol;
        step = f / df;
        /* damped so that p stays positive */
        if (step > 0.9 * p) step = 0.9 * p;
        g -= step;
        if (fabs(step) <= 1e-13 * p) break;
    }
    *gauge = g;
    return 1;
}

typedef struct {
    double g_a, g_b; /* gauge pressures [Pa] */
    double V_a, V_b; /* gas volumes including compliance [m^3] */
} GasState;

static int gas_state(const Instance *inst, double theta, double m_a, double m_b, GasState *gas) {
    const double x = V(inst, x_piston), stroke = V(inst, stroke);
    const double Va0 = rigid_volume(inst, stroke - x, +1.0, theta);
    const double Vb0 = rigid_volume(inst, x, -1.0, theta);
    if (!gas_pressure(inst, Va0, m_a, &gas->g_a) || !gas_pressure(inst, Vb0, m_b, &gas->g_b))
        return 0;
    gas->V_a = Va0 + V(inst, C_a) * gas->g_a;
    gas->V_b = Vb0 + V(inst, C_a) * gas->g_b;
    return 1;
}

/* Bending torque of the antagonistic chamber pair, torque = gauge pressure x dV/dtheta [N m]. */
static double bending_torque(const Instance *inst, const GasState *gas) {
    return V(inst, G_a) * (gas->g_a - gas->g_b);
}

/* Right-hand side for y = (theta, omega, m_a, m_b); returns 0 if the gas state is unphysical. */
static int derivatives(const Instance *inst, const double y[4], double dy[4]) {
    GasState gas;
    const double limit = V(inst, theta_max);
    if (!gas_state(inst, y[0], y[2], y[3], &gas)) return 0;
    dy[0] = y[1];
    dy[1] = (bending_torque(inst, &gas) + V(inst, tau_ext) - V(inst, k_bend) * y[0] -
             V(inst, d_bend) * y[1]) /
            bending_inertia(inst);
    if ((y[0] >= limit && y[1] >= 0.0 && dy[1] > 0.0) ||
        (y[0] <= -limit && y[1] <= 0.0 && dy[1] < 0.0)) {
        dy[1] = 0.0; /* resting against the mechanical limit */
    }
    dy[2] = -V(inst, leak_conductance) * gas.g_a;
    dy[3] = -V(inst, leak_conductance) * gas.g_b;
    return 1;
}

static int rk4_substep(Instance *inst, State *s, double dt) {
    double y[4] = {s->theta, s->omega, s->m_a, s->m_b}, k1[4], k2[4], k3[4], k4[4], t[4];
    const double limit = V(inst, theta_max);
    int j;
    if (!derivatives(inst, y, k1)) return 0;
    for (j = 0; j < 4; j++) t[j] = y[j] + 0.5 * dt * k1[j];
    if (!derivatives(inst, t, k2)) return 0;
    for (j = 0; j < 4; j++) t[j] = y[j] + 0.5 * dt * k2[j];
    if (!derivatives(inst, t, k3)) return 0;
    for (j = 0; j < 4; j++) t[j] = y[j] + dt * k3[j];
    if (!derivatives(inst, t, k4)) return 0;
    for (j = 0; j < 4; j++) y[j] += dt / 6.0 * (k1[j] + 2.0 * k2[j] + 2.0 * k3[j] + k4[j]);
    if (y[0] > limit) {
        y[0] = limit;
        if (y[1] > 0.0) y[1] = 0.0;
    } else if (y[0] < -limit) {
        y[0] = -limit;
        if (y[1] < 0.0) y[1] = 0.0;
    }
    s->theta = y[0];
    s->omega = y[1];
    s->m_a = y[2];
    s->m_b = y[3];
    return 1;
}

static int update_outputs(Instance *inst, const State *s) {
    GasState gas;
    if (!gas_state(inst, s->theta, s->m_a, s->m_b, &gas)) return 0;
    V(inst, kappa) = s->theta / V(inst, length);
    V(inst, theta) = s->theta;
    V(inst, theta_dot) = s->omega;
    V(inst, p_a) = gas.g_a;
    V(inst, p_b) = gas.g_b;
    V(inst, v_a) = gas.V_a;
    V(inst, v_b) = gas.V_b;
    return 1;
}

static int piston_inside_stroke(Instance *inst) {
    const double x = V(inst, x_piston), stroke = V(inst, stroke);
    if (x >= 0.0 && x <= stroke) return 1;
    log_message(inst, fmi2Error, "input x_piston = %g is outside the stroke [0, %g]", x, stroke);
    return 0;
}

fmi2Status model_initialize(Instance *inst) {
    State *s = (State *)inst->state;
    const double rho_atm = atmospheric_density(inst), stroke = V(inst, stroke);
    const double x_seal = V(inst, x_seal);
    if (x_seal > stroke) {
        log_message(inst, fmi2Error, "invalid parameter x_seal = %g: outside the stroke [0, %g]",
                    x_seal, stroke);
        return fmi2Error;
    }
    if (fabs(V(inst, theta_start)) > V(inst, theta_max)) {
        log_message(inst, fmi2Error, "invalid parameter theta_start = %g: beyond theta_max = %g",
                    V(inst, theta_start), V(inst, theta_max));
        return fmi2Error;
    }
    /* smallest rigid volume of a side: piston at the end stop that empties it, fully bent */
    if (!(V(inst, V_dead) + V(inst, V_ch0) - V(inst, G_a) * V(inst, theta_max) > 0.0)) {
        log_message(inst, fmi2Error,
                    "invalid parameters: a gas volume can reach zero (V_dead + V_ch0 - G_a "
                    "theta_max = %g m^3 must be positive)",
                    V(inst, V_dead) + V(inst, V_ch0) - V(inst, G_a) * V(inst, theta_max));
        return fmi2Error;
    }
    /* both circuits are sealed at atmospheric pressure with the piston at x_seal, unbent */
    s->m_a = rho_atm * rigid_volume(inst, stroke - x_seal, 1.0, 0.0);
    s->m_b = rho_atm * rigid_volume(inst, x_seal, -1.0, 0.0);
    s->theta = V(inst, theta_start);
    s->omega = 0.0;
    if (!piston_inside_stroke(inst)) return fmi2Error;
    if (!update_outputs(inst, s)) {
        log_message(inst, fmi2Error, "no physical gas state at the start (volume collapsed)");
        return fmi2Error;
    }
    return fmi2OK;
}

fmi2Status model_do_step(Instance *inst, double h) {
    State *s = (State *)inst->state;
    const int n = (int)ceil(h / V(inst, substep) - 1e-9);
    const double dt = h / (n > 0 ? n : 1);
    int j;
    if (!piston_inside_stroke(inst)) return fmi2Error;
    for (j = 0; j < (n > 0 ? n : 1); j++) {
        if (!rk4_substep(inst, s, dt)) {
            log_message(inst, fmi2Error,
                        "gas volume collapsed at t = %g (bend angle %g rad, piston %g m)",
                        inst->time + j * dt, s->theta, V(inst, x_piston));
            return fmi2Error;
        }
    }
    if (!isfinite(s->theta) || !isfinite(s->omega)) {
        log_message(inst, fmi2Error, "state became non-finite at t = %g", inst->time + h);
        return fmi2Error;
    }
    if (!update_outputs(inst, s)) {
        log_message(inst, fmi2Error, "gas volume collapsed at t = %g", inst->time + h);
        return fmi2Error;
    }
    return fmi2OK;
}
