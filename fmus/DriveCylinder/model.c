/* DriveCylinder physics: an armature-controlled DC motor turns a lead screw that pushes a
 * double-acting piston with Coulomb + viscous seal friction against the chamber pressures; hard
 * end stops at 0 and stroke. The actuator's own firmware is a discrete PID position servo with
 * derivative on measurement, a filtered derivative and conditional-integration anti-windup,
 * sampled every servo_period; its voltage is held between samples (ZOH).
 *
 * Lead screw: with load force F (pressure + seal friction, positive against +x), the motor-side
 * torque is r F / eta while the motor drives the load and r eta_b F while the load drives the
 * motor, eta_b = 2 - 1/eta (lead screw). Both are one law, a screw friction force
 * mu |F| sgn(v) with mu = 1/eta - 1, so the screw always dissipates and at eta <= 1/2
 * (eta_b <= 0) it self-locks: the load cannot back-drive it. sgn is smoothed like the seal's
 * Coulomb friction (a smoothstep over |v| < 2 v_stiction, velocity_sign), which leaves a creep of
 * order v_stiction.
 *
 * Integration: the common exponential RK4 integrates the linear electromechanics exactly (the
 * armature current with its stiff pole -R/L, coupled through back-EMF and torque to the rotor
 * speed and the piston position), so the substep is set by what stays explicit: the smoothed
 * Coulomb friction (its stability limit in mechanical_stability_limit; with the electrical pole
 * alone exact, the explicit coupling limited the substep to 1.25e-4 s for the same accuracy as
 * 5e-4 s now); substeps that start in the friction's band are split (friction_parts). Energies
 * are integrated with the states: E_electric = dE_stored + E_resistive + E_friction + E_screw +
 * W_gas holds for Kt = Ke (SI motor constants). */
#include <math.h>

#include "glue.h"

#define PI 3.14159265358979323846

enum { FAULT_END_STOP = 1, FAULT_REF_CLAMPED = 2, FAULT_STALL = 4 };

/* continuous states, in this order in State.y */
enum { I, W, X, E_ELECTRIC, E_RESISTIVE, E_FRICTION, E_SCREW, W_GAS, N_STATES };

typedef struct {
    double y[N_STATES]; /* i [A], w [rad/s], x [m], then the energies [J] */
    double integral;    /* servo integrator [V] */
    double d_filtered;  /* filtered derivative of the measured position [m/s] */
    double x_prev;      /* position at the previous servo sample [m] */
    double u;           /* voltage held until the next servo sample [V] */
    double to_sample;   /* time until the next servo sample [s] */
    double stalled_for; /* time saturated without moving [s] */
    int ref_clamped;
} State;

size_t model_state_size(void) { return sizeof(State); }

static double clamp(double value, double lo, double hi) {
    return value < lo ? lo : (value > hi ? hi : value);
}

/* Screw ratio: piston metres per rotor radian. */
static double screw_ratio(const Instance *inst) { return V(inst, lead) / (2.0 * PI); }

static double bore_area(const Instance *inst) {
    return 0.25 * PI * V(inst, bore) * V(inst, bore);
}

/* Screw friction coefficient mu = 1/eta - 1: F/eta forwards, (2 - 1/eta) F backwards. */
static double screw_friction_coefficient(const Instance *inst) {
    return 1.0 / V(inst, efficiency) - 1.0;
}

/* Smoothed sign of the piston velocity v, shared by the seal's Coulomb friction and the screw's:
 * the odd degree-7 smoothstep of u = v / (SIGN_ZONE v_stiction), monotonic, exactly +-1 for
 * |u| >= 1 and three times continuously differentiable there, slope SIGN_SLOPE / v_stiction at
 * rest. Unlike tanh it is constant outside the band |v| < SIGN_ZONE v_stiction, so away from rest
 * the friction is a constant force the solver integrates exactly; only inside the band does it
 * need finer substeps (friction_parts). */
#define SIGN_ZONE 2.0
#define SIGN_SLOPE (35.0 / 32.0) /* d sgn / d(v / v_stiction) at v = 0: 35/16 / SIGN_ZONE */
static double velocity_sign(const Instance *inst, double v) {
    const double u = v / (SIGN_ZONE * V(inst, v_stiction));
    double u2;
    if (u >= 1.0) return 1.0;
    if (u <= -1.0) return -1.0;
    u2 = u * u;
    return u * (35.0 + u2 * (-35.0 + u2 * (21.0 - 5.0 * u2))) / 16.0;
}

/* Seal friction force opposing the piston velocity v, smoothed Coulomb + viscous [N]; sgn is
 * velocity_sign(v). */
static double seal_friction(const Instance *inst, double v, double sgn) {
    return V(inst, F_coulomb) * sgn + V(inst, c_viscous) * v;
}

/* Lead screw friction force for a load F, sgn = velocity_sign(v) [N], always dissipative. */
static double screw_friction(const Instance *inst, double load, double sgn) {
    return screw_friction_coefficient(inst) * fabs(load) * sgn;
}

static double stored_energy(const Instance *inst, const double y[]) {
    return 0.5 * V(inst, L_motor) * y[I] * y[I] + 0.5 * V(inst, J) * y[W] * y[W];
}

/* The piston at rotor speed w: its velocity v [m/s], the smoothed sign of v, and the forces
 * against +x [N]: the chambers' pressure, the seal's friction, the load (the two together) and
 * the screw's friction. */
typedef struct {
    double v, sgn, pressure, seal, load, screw;
} PistonForces;

static PistonForces piston_forces(const Instance *inst, double w) {
    PistonForces f;
    f.v = screw_ratio(inst) * w;
    f.pressure = (V(inst, p_a) - V(inst, p_b)) * bore_area(inst);
    f.sgn = velocity_sign(inst, f.v);
    f.seal = seal_friction(inst, f.v, f.sgn);
    f.load = f.pressure + f.seal;
    f.screw = screw_friction(inst, f.load, f.sgn);
    return f;
}

int model_derivatives(const Instance *inst, const double y[], double dy[]) {
    const State *s = (const State *)inst->state;
    const double r = screw_ratio(inst);
    const PistonForces f = piston_forces(inst, y[W]);
    dy[I] = (s->u - V(inst, R_motor) * y[I] - V(inst, Ke) * y[W]) / V(inst, L_motor);
    dy[W] = (V(inst, Kt) * y[I] - V(inst, b_motor) * y[W] - r * (f.load + f.screw)) / V(inst, J);
    dy[X] = f.v;
    /* hard end stops: at a stop the screw cannot accelerate further into it */
    if (y[X] <= 0.0 && y[W] <= 0.0) {
        if (dy[W] < 0.0) dy[W] = 0.0;
        if (dy[X] < 0.0) dy[X] = 0.0;
    }
    if (y[X] >= V(inst, stroke) && y[W] >= 0.0) {
        if (dy[W] > 0.0) dy[W] = 0.0;
        if (dy[X] > 0.0) dy[X] = 0.0;
    }
    dy[E_ELECTRIC] = s->u * y[I];
    dy[E_RESISTIVE] = V(inst, R_motor) * y[I] * y[I];
    dy[E_FRICTION] = f.seal * f.v + V(inst, b_motor) * y[W] * y[W];
    dy[E_SCREW] = f.screw * f.v;
    dy[W_GAS] = f.pressure * f.v;
    return isfinite(dy[I]) && isfinite(dy[W]);
}

/* Inelastic impact at an end stop; the rotor's kinetic energy is lost to the stop. A piston
 * within STOP_CONTACT of a stop and moving into it is at the stop: in contact, the stages of a
 * substep that reach the stop stop the motion there (model_derivatives), which can leave the
 * piston a rounding-sized gap short of it, moving, for ever. */
#define STOP_CONTACT 1e-9 /* [m] */
void model_after_substep(Instance *inst, double dt) {
    State *s = (State *)inst->state;
    double *y = s->y;
    const double kinetic = 0.5 * V(inst, J) * y[W] * y[W];
    if (y[X] <= 0.0 || (y[X] < STOP_CONTACT && y[W] < 0.0)) {
        y[X] = 0.0;
        if (y[W] < 0.0) {
            y[W] = 0.0;
            y[E_FRICTION] += kinetic;
        }
    } else if (y[X] >= V(inst, stroke) || (y[X] > V(inst, stroke) - STOP_CONTACT && y[W] > 0.0)) {
        y[X] = V(inst, stroke);
        if (y[W] > 0.0) {
            y[W] = 0.0;
            y[E_FRICTION] += kinetic;
        }
    }
    s->to_sample -= dt;
}

double model_time_to_event(const Instance *inst) {
    return ((const State *)inst->state)->to_sample;
}

/* One sample of the servo firmware: PID from x_ref to the held motor voltage. */
void model_discrete_update(Instance *inst) {
    State *s = (State *)inst->state;
    const double Ts = V(inst, servo_period);
    const double u_max = V(inst, u_max);
    const double ref = clamp(V(inst, x_ref), 0.0, V(inst, stroke));
    const double x = s->y[X];
    const double error = ref - x;
    double proposed, u_unsat;
    s->to_sample += Ts;
    s->ref_clamped = ref != V(inst, x_ref);
    /* backward-Euler discretisation of s / (Tf s + 1) on the measurement: no derivative kick */
    s->d_filtered = (V(inst, Tf) * s->d_filtered + (x - s->x_prev)) / (V(inst, Tf) + Ts);
    s->x_prev = x;
    if (V(inst, enable) == 0.0) {
        s->integral = 0.0;
        s->u = 0.0;
        return;
    }
    proposed = s->integral + V(inst, Ki) * error * Ts;
    u_unsat = V(inst, Kp) * error + proposed - V(inst, Kd) * s->d_filtered;
    s->u = clamp(u_unsat, -u_max, u_max);
    /* conditional integration: integrate unless saturated and the error pushes further in */
    if (s->u == u_unsat || (u_unsat > u_max) != (error > 0.0)) {
        s->integral = clamp(proposed, -u_max, u_max);
    }
    /* stall: saturated and not advancing at 1 mm/s in the pushed direction (blocked or
     * back-driven by the chamber pressure) */
    if (fabs(s->u) >= u_max && (s->u > 0.0 ? 1.0 : -1.0) * screw_ratio(inst) * s->y[W] < 1e-3) {
        s->stalled_for += Ts;
    } else {
        s->stalled_for = 0.0;
    }
}

fmi2Status model_step_start(Instance *inst) {
    (void)inst;
    return fmi2OK;
}

fmi2Status model_outputs(Instance *inst) {
    const State *s = (const State *)inst->state;
    const double *y = s->y;
    int fault = 0;
    V(inst, x) = y[X];
    V(inst, v) = screw_ratio(inst) * y[W];
    V(inst, i_motor) = y[I];
    V(inst, u_motor) = s->u;
    if (y[X] <= 0.0 || y[X] >= V(inst, stroke)) fault |= FAULT_END_STOP;
    if (s->ref_clamped) fault |= FAULT_REF_CLAMPED;
    if (V(inst, stall_time) > 0.0 && s->stalled_for >= V(inst, stall_time)) fault |= FAULT_STALL;
    V(inst, fault) = fault;
    V(inst, E_electric) = y[E_ELECTRIC];
    V(inst, E_stored) = stored_energy(inst, y);
    V(inst, E_resistive) = y[E_RESISTIVE];
    V(inst, E_friction) = y[E_FRICTION];
    V(inst, E_screw) = y[E_SCREW];
    V(inst, W_gas) = y[W_GAS];
    return fmi2OK;
}

/* The substep beyond which the explicit part of the exponential RK4 diverges [s]: 2.5 / |lambda|
 * (RK4's stability region contains the left half-disc of radius 2.5), with lambda the fastest
 * rate left in the explicit part: the linearised Coulomb seal and screw friction (slope
 * SIGN_SLOPE F / v_stiction at the largest load the motor can hold, its stall force
 * Kt u_max / (R r)), reflected through the screw. The electromechanics (current, back-EMF,
 * viscous friction) are the linear block, integrated exactly. The bound holds for a substep that
 * is not split; inside the friction's band friction_parts splits substeps far below it, so it is
 * conservative. */
static double mechanical_stability_limit(const Instance *inst) {
    const double r = screw_ratio(inst);
    const double stall_force = V(inst, Kt) * V(inst, u_max) / (V(inst, R_motor) * r);
    const double friction_slope =
        SIGN_SLOPE * (V(inst, F_coulomb) + screw_friction_coefficient(inst) * stall_force) /
        V(inst, v_stiction);
    return 2.5 / (r * r * friction_slope / V(inst, J));
}

/* Into how many parts a substep of length h must be split at the current state (the solver's
 * `parts`). Inside the friction's band (|v| < SIGN_ZONE v_stiction, or reached within the substep
 * at the acceleration a) the Coulomb seal and screw friction are both stiff, with the rate lambda
 * = SIGN_SLOPE (F_coulomb + mu |load|) / v_stiction reflected through the screw, and fast: the
 * band is crossed in about v_stiction / a. Parts keep h (lambda + a / v_stiction) at most
 * FRICTION_STEP (0.25: the default drive then agrees with a 4x finer reference within 1e-6 of
 * each signal's range in the closed loop; 0.5 gives 2.4e-6). a is the larger of the acceleration
 * now and the one once the current follows the held voltage (within L/R, a fraction of the
 * substep): a servo sample that changes the voltage starts the piston from rest within the
 * substep. Outside the band the friction is constant and one part is exact; against an end stop
 * the piston stays put and one part is kept. */
#define FRICTION_STEP 0.25
static int friction_parts(const Instance *inst, double h) {
    const State *s = (const State *)inst->state;
    const double r = screw_ratio(inst), vs = V(inst, v_stiction);
    const PistonForces f = piston_forces(inst, s->y[W]);
    const double v = f.v;
    const double slope =
        SIGN_SLOPE * (V(inst, F_coulomb) + screw_friction_coefficient(inst) * fabs(f.load)) / vs;
    const double others = -V(inst, b_motor) * s->y[W] - r * (f.load + f.screw);
    const double a_now = fabs(r * (V(inst, Kt) * s->y[I] + others) / V(inst, J));
    const double i_held = (s->u - V(inst, Ke) * s->y[W]) / V(inst, R_motor);
    const double a_held = fabs(r * (V(inst, Kt) * i_held + others) / V(inst, J));
    const double a = a_now > a_held ? a_now : a_held;
    double parts;
    if (fabs(v) >= SIGN_ZONE * vs + a * h) return 1;
    /* held against an end stop the piston does not move: nothing to resolve */
    if ((s->y[X] <= 0.0 && s->y[W] <= 0.0) || (s->y[X] >= V(inst, stroke) && s->y[W] >= 0.0)) {
        return 1;
    }
    parts = h * (r * r * slope / V(inst, J) + a / vs) / FRICTION_STEP;
    return parts < MAX_PARTS ? (int)ceil(parts) : MAX_PARTS; /* NaN too: no int overflow */
}

/* The linear electromechanics, integrated exactly by the solver: armature current, rotor speed
 * and piston position, with the motor's resistance, back-EMF and torque, the rotor's and the
 * seal's viscous friction. The held voltage, the chamber pressures and the Coulomb and screw
 * friction stay in the explicit part. */
static void linear_block(const Instance *inst, OdeSystem *ode) {
    const double r = screw_ratio(inst), L = V(inst, L_motor), J = V(inst, J);
    ode->nb = 3;
    ode->A[I][I] = -V(inst, R_motor) / L;
    ode->A[I][W] = -V(inst, Ke) / L;
    ode->A[W][I] = V(inst, Kt) / J;
    ode->A[W][W] = -(V(inst, b_motor) + r * r * V(inst, c_viscous)) / J;
    ode->A[X][W] = r;
}

fmi2Status model_initialize(Instance *inst, OdeSystem *ode) {
    State *s = (State *)inst->state;
    int j;
    if (V(inst, x_start) > V(inst, stroke)) {
        log_message(inst, fmi2Error, "invalid parameter x_start = %g: outside the stroke [0, %g]",
                    V(inst, x_start), V(inst, stroke));
        return fmi2Error;
    }
    if (V(inst, substep) > V(inst, servo_period)) {
        log_message(inst, fmi2Error, "invalid parameter substep = %g: longer than servo_period %g",
                    V(inst, substep), V(inst, servo_period));
        return fmi2Error;
    }
    ode->stability_limit = mechanical_stability_limit(inst);
    if (V(inst, substep) > ode->stability_limit) {
        log_message(inst, fmi2Error,
                    "invalid parameter substep = %g: beyond the stability limit %g s of the "
                    "mechanics (Coulomb seal and screw friction reflected through the screw)",
                    V(inst, substep), ode->stability_limit);
        return fmi2Error;
    }
    for (j = 0; j < N_STATES; j++) s->y[j] = 0.0;
    s->y[X] = V(inst, x_start);
    s->x_prev = s->y[X];
    s->integral = 0.0;
    s->d_filtered = 0.0;
    s->u = 0.0;
    s->to_sample = 0.0;
    s->stalled_for = 0.0;
    s->ref_clamped = 0;
    ode->n = N_STATES;
    ode->y = s->y;
    linear_block(inst, ode);
    ode->parts = friction_parts;
    ode->max_substep = V(inst, substep);
    return model_outputs(inst);
}
