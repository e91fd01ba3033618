/* DriveCylinder physics (PHYSICS.md section 1): an armature-controlled DC motor turns a lead
 * screw that pushes a double-acting piston with Coulomb + viscous seal friction against the
 * chamber pressures; hard end stops at 0 and stroke. The actuator's own firmware is a discrete PID
 * position servo with derivative on measurement, a filtered derivative and conditional-integration
 * anti-windup, sampled every servo_period. Continuous states are integrated with fixed RK4
 * substeps no longer than `substep`; the servo voltage is held between samples (ZOH). */
#include <math.h>

#include "glue.h"

#define PI 3.14159265358979323846

enum { FAULT_END_STOP = 1, FAULT_REF_CLAMPED = 2, FAULT_STALL = 4 };

typedef struct {
    double i, w, x;     /* motor current [A], rotor speed [rad/s], piston position [m] */
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

/* Seal friction force opposing the piston velocity v, smoothed Coulomb + viscous [N]. */
static double seal_friction(const Instance *inst, double v) {
    return V(inst, F_coulomb) * tanh(v / V(inst, v_stiction)) + V(inst, c_viscous) * v;
}

/* Right-hand side of the motor/screw/piston equations for y = (i, w, x). */
static void derivatives(const Instance *inst, const double y[3], double u, double dy[3]) {
    const double r = screw_ratio(inst);
    const double v = r * y[1];
    const double load = (V(inst, p_a) - V(inst, p_b)) * bore_area(inst) + seal_friction(inst, v);
    const double load_torque = r / V(inst, efficiency) * load;
    dy[0] = (u - V(inst, R_motor) * y[0] - V(inst, Ke) * y[1]) / V(inst, L_motor);
    dy[1] = (V(inst, Kt) * y[0] - V(inst, b_motor) * y[1] - load_torque) / V(inst, J);
    dy[2] = v;
    /* hard end stops: at a stop the screw cannot accelerate further into it */
    if (y[2] <= 0.0 && y[1] <= 0.0) {
        if (dy[1] < 0.0) dy[1] = 0.0;
        if (dy[2] < 0.0) dy[2] = 0.0;
    }
    if (y[2] >= V(inst, stroke) && y[1] >= 0.0) {
        if (dy[1] > 0.0) dy[1] = 0.0;
        if (dy[2] > 0.0) dy[2] = 0.0;
    }
}

/* One RK4 substep of length dt, then an inelastic impact at an end stop. */
static void rk4_substep(Instance *inst, State *s, double dt) {
    double y[3] = {s->i, s->w, s->x}, k1[3], k2[3], k3[3], k4[3], t[3];
    int j;
    derivatives(inst, y, s->u, k1);
    for (j = 0; j < 3; j++) t[j] = y[j] + 0.5 * dt * k1[j];
    derivatives(inst, t, s->u, k2);
    for (j = 0; j < 3; j++) t[j] = y[j] + 0.5 * dt * k2[j];
    derivatives(inst, t, s->u, k3);
    for (j = 0; j < 3; j++) t[j] = y[j] + dt * k3[j];
    derivatives(inst, t, s->u, k4);
    for (j = 0; j < 3; j++) y[j] += dt / 6.0 * (k1[j] + 2.0 * k2[j] + 2.0 * k3[j] + k4[j]);
    if (y[2] <= 0.0) {
        y[2] = 0.0;
        if (y[1] < 0.0) y[1] = 0.0;
    } else if (y[2] >= V(inst, stroke)) {
        y[2] = V(inst, stroke);
        if (y[1] > 0.0) y[1] = 0.0;
    }
    s->i = y[0];
    s->w = y[1];
    s->x = y[2];
}

/* One sample of the servo firmware: PID from x_ref to the held motor voltage. */
static void servo_sample(Instance *inst, State *s) {
    const double Ts = V(inst, servo_period);
    const double u_max = V(inst, u_max);
    const double ref = clamp(V(inst, x_ref), 0.0, V(inst, stroke));
    const double error = ref - s->x;
    double proposed, u_unsat;
    s->ref_clamped = ref != V(inst, x_ref);
    /* backward-Euler discretisation of s / (Tf s + 1) on the measurement: no derivative kick */
    s->d_filtered = (V(inst, Tf) * s->d_filtered + (s->x - s->x_prev)) / (V(inst, Tf) + Ts);
    s->x_prev = s->x;
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
    if (fabs(s->u) >= u_max && (s->u > 0.0 ? 1.0 : -1.0) * screw_ratio(inst) * s->w < 1e-3) {
        s->stalled_for += Ts;
    } else {
        s->stalled_for = 0.0;
    }
}

static void update_outputs(Instance *inst, const State *s) {
    int fault = 0;
    V(inst, x) = s->x;
    V(inst, v) = screw_ratio(inst) * s->w;
    V(inst, i_motor) = s->i;
    V(inst, u_motor) = s->u;
    if (s->x <= 0.0 || s->x >= V(inst, stroke)) fault |= FAULT_END_STOP;
    if (s->ref_clamped) fault |= FAULT_REF_CLAMPED;
    if (V(inst, stall_time) > 0.0 && s->stalled_for >= V(inst, stall_time)) fault |= FAULT_STALL;
    V(inst, fault) = fault;
}

fmi2Status model_initialize(Instance *inst) {
    State *s = (State *)inst->state;
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
    s->i = 0.0;
    s->w = 0.0;
    s->x = V(inst, x_start);
    s->x_prev = s->x;
    s->integral = 0.0;
    s->d_filtered = 0.0;
    s->u = 0.0;
    s->to_sample = 0.0;
    s->stalled_for = 0.0;
    s->ref_clamped = 0;
    update_outputs(inst, s);
    return fmi2OK;
}

fmi2Status model_do_step(Instance *inst, double h) {
    State *s = (State *)inst->state;
    double remaining = h;
    /* tolerance so that a step of exactly n servo periods ends on, not just before, a sample */
    const double eps = 1e-12 * V(inst, servo_period);
    while (remaining > eps) {
        double dt;
        if (s->to_sample <= eps) {
            servo_sample(inst, s);
            s->to_sample += V(inst, servo_period);
        }
        dt = remaining < s->to_sample ? remaining : s->to_sample;
        if (dt > V(inst, substep)) {
            /* equal substeps to the next event */
            const double n = ceil(dt / V(inst, substep) - 1e-9);
            dt = dt / n;
        }
        rk4_substep(inst, s, dt);
        remaining -= dt;
        s->to_sample -= dt;
    }
    if (!isfinite(s->x) || !isfinite(s->w) || !isfinite(s->i)) {
        log_message(inst, fmi2Error, "state became non-finite at t = %g (check the parameters)",
                    inst->time + h);
        return fmi2Error;
    }
    update_outputs(inst, s);
    return fmi2OK;
}
