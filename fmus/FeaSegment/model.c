/* FeaSegment physics: one bidirectional fluidic elastomer segment and the two sealed gas circuits
 * that drive it. Side i in {a, b} is cylinder chamber + tubing + channel of volume
 *   V_i = A s_i(x) + V_dead + V_ch0 + sign_i G(g_i) theta + C_a g_i,  s_a = stroke - x, s_b = x,
 * sign_a = +1, sign_b = -1, g_i the gauge pressure. The bend angle obeys
 *   I theta'' + d theta' + k theta = H(g_a) - H(g_b) + tau_ext,   H(g) = integral_0^g G(s) ds,
 * clamped to |theta| <= theta_max.
 *
 * The gas circuit's functions are shared with ArmBody (fmus/common/gas_circuit.h).
 *
 * Vacuum: a thin-walled channel below atmospheric pressure partially collapses and transmits less
 * torque per pascal [estimate]. Its bend sensitivity is G(g) = G_a for g >= 0 and
 * G_a (beta + (1 - beta) exp(g / p_collapse)) for g < 0, beta = vacuum_factor: it falls smoothly
 * from G_a to beta G_a over a few p_collapse of vacuum. Energy consistency (virtual work): a
 * channel whose dV/dtheta depends on its pressure stores membrane energy
 *   Psi = C_a g^2 / 2 + sign theta (g G(g) - H(g)),
 * and the torque that makes gas work, bending work and dPsi/dt balance exactly is sign H(g), which
 * is G_a g under pressure and tends to beta G_a g under deep vacuum.
 *
 * Inertia: a uniform PCC segment of mass m bent by theta has lateral deflection
 * y(s) = theta s^2 / (2 L) at small angles, so its kinetic energy is
 * (1/2) (m/L) int_0^L (theta' s^2 / (2 L))^2 ds = (1/2) (m L^2 / 20) theta'^2: I = m L^2 / 20
 * (m L^2 / 3 is a rigid rod pivoting about its base).
 *
 * Gas: ideal gas with polytropic exponent n and heat exchange with the walls at T_gas. The state
 * per side is its mass m and the adiabatic invariant theta_s = T (V/m)^(n-1), so that
 * p = R theta_s (m/V)^n; a fast move is polytropic, and the walls relax the temperature with time
 * constant tau_thermal: d theta_s/dt = (T_gas (V/m)^(n-1) - theta_s) / tau_thermal. n = 1 is
 * isothermal. A leak drains mass isentropically. A change of the input x_piston between steps is
 * a sudden (isentropic) compression.
 *
 * Energy (outputs): W_piston + W_ext = dE_stored + E_dissipated exactly without a leak, with
 * E_stored = sum_i (E_gas_i + Psi_i) + k theta^2 / 2 + I theta'^2 / 2, E_gas the gas's free
 * energy relative to the atmosphere (-m R T ln V + p_atm V isothermal, p V / (n - 1) + p_atm V
 * polytropic), E_dissipated = damping + heat to the walls + impacts at the limit. */
#include <math.h>
#include <string.h>

#include "gas_circuit.h"
#include "glue.h"

#define PI 3.14159265358979323846

/* continuous states, in this order in State.y */
enum { THETA, OMEGA, M_A, M_B, S_A, S_B, E_DAMP, E_HEAT, W_EXT, N_STATES };

typedef struct {
    double y[N_STATES]; /* theta [rad], omega [rad/s], masses [kg], theta_s [K m^3(n-1)/kg^(n-1)],
                           energies [J] */
    double x;           /* piston position applied in this step [m] */
    double W_piston;    /* work done by the piston on the gas [J] */
    double E_impact;    /* kinetic energy lost at the mechanical limit [J] */
    /* the last gas state solved outside the integrator (model_outputs at the end of a step, the
     * isentropic compression at the start of the next) and its stored energy, with the (x, y) it
     * was solved at exactly: the compression's work starts from it, and the first stage of the
     * next substep, which evaluates the same (x, y), takes it instead of solving again (the same
     * bits: the solve is a deterministic function of (x, y)) */
    double cached_y[N_STATES], cached_x, cached_energy;
    GasState cached_gas;
    int cached;
    GasCircuit circuit; /* the gas circuit's parameters (gas_circuit.h), set at initialisation */
} State;

size_t model_state_size(void) { return sizeof(State); }

static double bending_inertia(const Instance *inst) {
    return V(inst, mass) * V(inst, length) * V(inst, length) / 20.0;
}

static const GasCircuit *circuit_of(const Instance *inst) {
    return &((const State *)inst->state)->circuit;
}

static int gas_state_of(const Instance *inst, double x, const double y[], GasState *gas) {
    return gas_state(circuit_of(inst), x, y[THETA], &y[M_A], &y[S_A], gas);
}

/* Heat flowing from the gas of one side to the walls [W] (zero when isothermal). */
static double heat_to_walls(const Instance *inst, double m, double theta_s, double vol) {
    const double n = V(inst, n_poly);
    if (n == 1.0) return 0.0;
    return m * V(inst, R_gas) / (n - 1.0) * (theta_s * pow(m / vol, n - 1.0) - V(inst, T_gas)) /
           V(inst, tau_thermal);
}

int model_derivatives(const Instance *inst, const double y[], double dy[]) {
    const State *s = (const State *)inst->state;
    const double limit = V(inst, theta_max), n = V(inst, n_poly);
    GasState gas;
    int side;
    if (s->cached && s->cached_x == s->x && memcmp(s->cached_y, y, sizeof s->y) == 0) {
        gas = s->cached_gas;
    } else if (!gas_state_of(inst, s->x, y, &gas)) {
        return 0;
    }
    dy[THETA] = y[OMEGA];
    dy[OMEGA] = (gas_bending_torque(&gas) + V(inst, tau_ext) - V(inst, k_bend) * y[THETA] -
                 V(inst, d_bend) * y[OMEGA]) /
                bending_inertia(inst);
    if ((y[THETA] >= limit && y[OMEGA] >= 0.0 && dy[OMEGA] > 0.0) ||
        (y[THETA] <= -limit && y[OMEGA] <= 0.0 && dy[OMEGA] < 0.0)) {
        dy[OMEGA] = 0.0; /* resting against the mechanical limit */
    }
    dy[E_HEAT] = 0.0;
    for (side = 0; side < 2; side++) {
        const double m = y[M_A + side], ts = y[S_A + side];
        dy[M_A + side] = -V(inst, leak_conductance) * gas.g[side];
        dy[S_A + side] =
            n == 1.0 ? 0.0
                     : (V(inst, T_gas) * pow(gas.V[side] / m, n - 1.0) - ts) / V(inst, tau_thermal);
        dy[E_HEAT] += heat_to_walls(inst, m, ts, gas.V[side]);
    }
    dy[E_DAMP] = V(inst, d_bend) * y[OMEGA] * y[OMEGA];
    dy[W_EXT] = V(inst, tau_ext) * y[OMEGA];
    return 1;
}

/* Energy stored in gas, membranes, bending spring and motion [J], given the gas state of y. */
static double energy_of(const Instance *inst, const double y[], const GasState *gas) {
    double total = 0.5 * V(inst, k_bend) * y[THETA] * y[THETA] +
                   0.5 * bending_inertia(inst) * y[OMEGA] * y[OMEGA];
    int side;
    for (side = 0; side < 2; side++) {
        total += gas_free_energy(circuit_of(inst), gas, side, y[M_A + side], y[S_A + side]) +
                 gas_membrane_energy(circuit_of(inst), gas, side, y[THETA]);
    }
    return total;
}

/* Energy stored at piston position x [J]; 0 if no physical gas state exists there. */
static int stored_energy(const Instance *inst, double x, const double y[], double *energy) {
    GasState gas;
    if (!gas_state_of(inst, x, y, &gas)) return 0;
    *energy = energy_of(inst, y, &gas);
    return 1;
}

/* Inelastic stop at the mechanical limit. */
void model_after_substep(Instance *inst, double dt) {
    State *s = (State *)inst->state;
    const double limit = V(inst, theta_max);
    double *y = s->y;
    (void)dt;
    if (y[THETA] > limit || y[THETA] < -limit) {
        y[THETA] = y[THETA] > limit ? limit : -limit;
        if (y[OMEGA] * y[THETA] > 0.0) {
            s->E_impact += 0.5 * bending_inertia(inst) * y[OMEGA] * y[OMEGA];
            y[OMEGA] = 0.0;
        }
    }
}

double model_time_to_event(const Instance *inst) {
    (void)inst;
    return INFINITY;
}

void model_discrete_update(Instance *inst) { (void)inst; }

/* x_piston within the stroke, tolerating rounding-sized excursions (an input interpolated to the
 * end of the stroke may land one rounding error past it): up to PISTON_TOLERANCE x stroke it is
 * clamped silently, beyond that it is an error. */
#define PISTON_TOLERANCE 1e-9

static int applied_piston_position(Instance *inst, double *x) {
    const double raw = V(inst, x_piston), stroke = V(inst, stroke);
    const double tolerance = PISTON_TOLERANCE * stroke;
    if (raw < -tolerance || raw > stroke + tolerance) {
        log_message(inst, fmi2Error,
                    "input x_piston = %.10g is outside the stroke [0, %g] (tolerance %g m)", raw,
                    stroke, tolerance);
        return 0;
    }
    *x = raw < 0.0 ? 0.0 : (raw > stroke ? stroke : raw);
    return 1;
}

/* Keeps the gas state just solved at (s->x, s->y) and its stored energy. */
static void remember(State *s, const GasState *gas, double energy) {
    s->cached = 1;
    s->cached_x = s->x;
    s->cached_energy = energy;
    s->cached_gas = *gas;
    memcpy(s->cached_y, s->y, sizeof s->y);
}

/* A new piston position is a sudden isentropic compression: the work done on the gas is the
 * change of the stored energy at fixed masses, invariants and bend. */
fmi2Status model_step_start(Instance *inst) {
    State *s = (State *)inst->state;
    GasState gas;
    double x, before, after;
    if (!applied_piston_position(inst, &x)) return fmi2Error;
    if (x == s->x) return fmi2OK;
    if (s->cached && s->cached_x == s->x && memcmp(s->cached_y, s->y, sizeof s->y) == 0) {
        before = s->cached_energy; /* bit for bit what stored_energy would return */
    } else if (!stored_energy(inst, s->x, s->y, &before)) {
        before = NAN;
    }
    if (!isfinite(before) || !gas_state_of(inst, x, s->y, &gas)) {
        log_message(inst, fmi2Error, "no physical gas state at piston position %g m", x);
        return fmi2Error;
    }
    after = energy_of(inst, s->y, &gas);
    s->W_piston += after - before;
    s->x = x;
    remember(s, &gas, after);
    return fmi2OK;
}

fmi2Status model_outputs(Instance *inst) {
    State *s = (State *)inst->state;
    const double *y = s->y;
    GasState gas;
    double energy;
    if (!gas_state_of(inst, s->x, y, &gas)) {
        log_message(inst, fmi2Error,
                    "no physical gas state (bend angle %g rad, piston %g m): a volume collapsed",
                    y[THETA], s->x);
        return fmi2Error;
    }
    V(inst, kappa) = y[THETA] / V(inst, length);
    V(inst, theta) = y[THETA];
    V(inst, theta_dot) = y[OMEGA];
    V(inst, p_a) = gas.g[0];
    V(inst, p_b) = gas.g[1];
    V(inst, v_a) = gas.V[0];
    V(inst, v_b) = gas.V[1];
    energy = energy_of(inst, y, &gas); /* the gas state just solved: one solve, not two */
    remember(s, &gas, energy);
    V(inst, E_stored) = energy;
    V(inst, W_piston) = s->W_piston;
    V(inst, W_ext) = y[W_EXT];
    V(inst, E_dissipated) = y[E_DAMP] + y[E_HEAT] + s->E_impact;
    return fmi2OK;
}

/* The substep beyond which the exponential RK4 diverges [s]. The bending mode's spring and
 * damping are the linear block, integrated exactly (its inertial pole -d/I, about -1100 1/s, set
 * the substep to 5e-4 s when it was explicit); what stays explicit is the gas's bending
 * stiffness, bounded by k_gas = n p_max G_a^2 (1 / V_a + 1 / V_b) <= 2 n p_max G_a^2 / V_min over
 * the smallest volumes and the largest compression ratio. For the ETDRK4 amplification matrix
 * of theta'' = -(k theta + d theta' + k_gas theta) / I with k and d exact, the spectral radius
 * stays below 1 while h <= 1.5 / sqrt(k_gas / I) over damping ratios from overdamped to
 * d = 1e-4 (computed numerically; the bound is within 1.5x of the true limit there). With
 * n > 1 the heat exchange 1 / tau_thermal is explicit too: 2.5 tau_thermal. */
static double bending_stability_limit(const Instance *inst) {
    const double I = bending_inertia(inst), n = V(inst, n_poly);
    const double V_min = V(inst, V_dead) + V(inst, V_ch0) - V(inst, G_a) * V(inst, theta_max);
    const double V_max =
        gas_base_volume(circuit_of(inst), V(inst, stroke)) + V(inst, G_a) * V(inst, theta_max);
    const double p_max = V(inst, p_atm) * pow(V_max / V_min, n);
    const double k_gas = 2.0 * n * p_max * V(inst, G_a) * V(inst, G_a) / V_min;
    double limit = k_gas > 0.0 ? 1.5 / sqrt(k_gas / I) : INFINITY;
    if (n != 1.0 && 2.5 * V(inst, tau_thermal) < limit) limit = 2.5 * V(inst, tau_thermal);
    return limit;
}

/* The gas circuit's parameters, from the instance's. */
static GasCircuit circuit_from_parameters(const Instance *inst) {
    GasCircuit c;
    c.area = 0.25 * PI * V(inst, bore) * V(inst, bore);
    c.stroke = V(inst, stroke);
    c.V_dead = V(inst, V_dead);
    c.V_ch0 = V(inst, V_ch0);
    c.C_a = V(inst, C_a);
    c.G_a = V(inst, G_a);
    c.vacuum_factor = V(inst, vacuum_factor);
    c.p_collapse = V(inst, p_collapse);
    c.p_atm = V(inst, p_atm);
    c.R_gas = V(inst, R_gas);
    c.n_poly = V(inst, n_poly);
    return c;
}

/* The bending mode's linear part, integrated exactly by the solver: theta' = omega,
 * omega' = -(k theta + d omega) / I; the gas torque and tau_ext stay explicit. */
static void linear_block(const Instance *inst, OdeSystem *ode) {
    const double I = bending_inertia(inst);
    ode->nb = 2;
    ode->A[THETA][OMEGA] = 1.0;
    ode->A[OMEGA][THETA] = -V(inst, k_bend) / I;
    ode->A[OMEGA][OMEGA] = -V(inst, d_bend) / I;
}

fmi2Status model_initialize(Instance *inst, OdeSystem *ode) {
    State *s = (State *)inst->state;
    const double stroke = V(inst, stroke), x_seal = V(inst, x_seal), n = V(inst, n_poly);
    const double V_min = V(inst, V_dead) + V(inst, V_ch0) - V(inst, G_a) * V(inst, theta_max);
    int side, j;
    s->circuit = circuit_from_parameters(inst);
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
    if (!(V_min > 0.0)) {
        log_message(inst, fmi2Error,
                    "invalid parameters: a gas volume can reach zero (V_dead + V_ch0 - G_a "
                    "theta_max = %g m^3 must be positive)",
                    V_min);
        return fmi2Error;
    }
    /* the pressure-volume relation stays monotone (one gas state per volume) up to 4 atm if the
     * collapse does not shrink dV/dg below zero faster than the gas can follow */
    if (4.0 * n * V(inst, p_atm) *
            (V(inst, G_a) * (1.0 - V(inst, vacuum_factor)) * V(inst, theta_max) /
                 V(inst, p_collapse) -
             V(inst, C_a)) >=
        V_min) {
        log_message(inst, fmi2Error,
                    "invalid parameters: p_collapse = %g Pa is too sharp for G_a, vacuum_factor "
                    "and theta_max (the channel volume would not be monotone in pressure)",
                    V(inst, p_collapse));
        return fmi2Error;
    }
    ode->stability_limit = bending_stability_limit(inst);
    if (V(inst, substep) > ode->stability_limit) {
        log_message(inst, fmi2Error,
                    "invalid parameter substep = %g: beyond the stability limit %g s of the "
                    "bending mode's gas stiffness (inertia and gas stiffness)",
                    V(inst, substep), ode->stability_limit);
        return fmi2Error;
    }
    for (j = 0; j < N_STATES; j++) s->y[j] = 0.0;
    /* both circuits are sealed at atmospheric pressure and T_gas with the piston at x_seal,
     * unbent */
    for (side = 0; side < 2; side++) {
        const double v_seal =
            gas_base_volume(&s->circuit, gas_swept_length(&s->circuit, x_seal, side));
        const double m = V(inst, p_atm) * v_seal / (V(inst, R_gas) * V(inst, T_gas));
        s->y[M_A + side] = m;
        s->y[S_A + side] = V(inst, T_gas) * pow(v_seal / m, n - 1.0);
    }
    s->y[THETA] = V(inst, theta_start);
    s->W_piston = 0.0;
    s->E_impact = 0.0;
    s->cached = 0;
    if (!applied_piston_position(inst, &s->x)) return fmi2Error;
    ode->n = N_STATES;
    ode->y = s->y;
    linear_block(inst, ode);
    ode->max_substep = V(inst, substep);
    return model_outputs(inst);
}
