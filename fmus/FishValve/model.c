/* FishValve physics: the 3/2 solenoid valve of one tail channel of the soft fish (README, "The
 * soft fish"). The spool connects the channel to the supply (open) or to the vent (closed).
 *
 * Why the valve publishes areas, not flows: the flow through a nozzle is an algebraic function of
 * the pressures on both sides, and the channel's pressure is the fastest state of the fish: near
 * equal pressures the flow ~ sqrt(dp) has an unbounded slope, so the channel settles on its supply
 * or on ambient with a time constant that goes to zero (FishBody/model.c). A valve that read the
 * channel pressure at a communication point and published the flow for the next step closed that
 * loop explicitly over two 1 ms steps: the vented channels then oscillated by +-7 kPa with a period
 * of six steps, drew gas back in (the vented mass fell), and a large nozzle filled a channel beyond
 * the supply pressure. So the valve is the spool and its geometry: it publishes the effective areas
 * CdA_in = opening Cd_nozzle A_nozzle and CdA_vent = (1 - opening) Cd_vent A_vent, and FishBody,
 * which owns the channel's gas, integrates the nozzle flows with it in its substeps. The areas
 * change only with the spool (a 2 ms lag after a 5 ms dead time), so holding them over a step is
 * accurate. The same valve model serves both channels (two instances): one physics, two sides.
 *
 * Spool: a command change takes effect after the dead time t_delay (commands are queued, so a
 * pulse shorter than the delay is still delivered, delayed); the spool then follows the commanded
 * end with a first-order lag tau_valve, integrated exactly (the solver's stiff rate -1/tau). */
#include <math.h>

#include "glue.h"

#define PI 3.14159265358979323846
#define MAX_PENDING 16

enum { OPENING, N_STATES };

typedef struct {
    double y[N_STATES];             /* spool position [1] */
    double t;                       /* time inside the current step [s] */
    int commanded;                  /* last command read from the input */
    int target;                     /* command the spool is travelling to (after the delay) */
    int n_pending;                  /* queued command changes, oldest first */
    double pending_time[MAX_PENDING];
    int pending_value[MAX_PENDING];
} State;

size_t model_state_size(void) { return sizeof(State); }

static double area(double diameter) { return 0.25 * PI * diameter * diameter; }

int model_derivatives(const Instance *inst, const double y[], double dy[]) {
    const State *s = (const State *)inst->state;
    dy[OPENING] = ((double)s->target - y[OPENING]) / V(inst, tau_valve);
    return 1;
}

double model_time_to_event(const Instance *inst) {
    const State *s = (const State *)inst->state;
    if (s->n_pending == 0) return INFINITY;
    return s->pending_time[0] - s->t;
}

/* Applies every queued command change that is due. */
void model_discrete_update(Instance *inst) {
    State *s = (State *)inst->state;
    const double eps = 1e-12 * (1.0 + fabs(s->t));
    int k;
    while (s->n_pending > 0 && s->pending_time[0] <= s->t + eps) {
        s->target = s->pending_value[0];
        for (k = 1; k < s->n_pending; k++) {
            s->pending_time[k - 1] = s->pending_time[k];
            s->pending_value[k - 1] = s->pending_value[k];
        }
        s->n_pending--;
    }
}

void model_after_substep(Instance *inst, double dt) {
    State *s = (State *)inst->state;
    s->t += dt;
    /* the lag is exact, but rounding must not leave the spool outside its travel */
    if (s->y[OPENING] < 0.0) s->y[OPENING] = 0.0;
    if (s->y[OPENING] > 1.0) s->y[OPENING] = 1.0;
}

/* Reads the command; a change is queued to take effect t_delay later. */
fmi2Status model_step_start(Instance *inst) {
    State *s = (State *)inst->state;
    const int command = V(inst, open) != 0.0;
    s->t = inst->time;
    if (command == s->commanded) return fmi2OK;
    if (s->n_pending == MAX_PENDING) {
        log_message(inst, fmi2Error,
                    "input open toggled more than %d times within t_delay = %g s", MAX_PENDING,
                    V(inst, t_delay));
        return fmi2Error;
    }
    s->pending_time[s->n_pending] = s->t + V(inst, t_delay);
    s->pending_value[s->n_pending] = command;
    s->n_pending++;
    s->commanded = command;
    if (V(inst, t_delay) == 0.0) model_discrete_update(inst);
    return fmi2OK;
}

fmi2Status model_outputs(Instance *inst) {
    const State *s = (const State *)inst->state;
    const double x = s->y[OPENING];
    V(inst, CdA_in) = x * V(inst, Cd_nozzle) * area(V(inst, d_nozzle));
    V(inst, CdA_vent) = (1.0 - x) * V(inst, Cd_vent) * area(V(inst, d_vent));
    V(inst, opening) = x;
    return fmi2OK;
}

fmi2Status model_initialize(Instance *inst, OdeSystem *ode) {
    State *s = (State *)inst->state;
    const int command = V(inst, open) != 0.0;
    /* the valve starts at rest in its commanded position */
    s->y[OPENING] = command ? 1.0 : 0.0;
    s->commanded = s->target = command;
    s->n_pending = 0;
    s->t = inst->time;
    ode->n = N_STATES;
    ode->y = s->y;
    ode->lambda[OPENING] = -1.0 / V(inst, tau_valve);
    ode->max_substep = V(inst, substep);
    ode->stability_limit = INFINITY; /* the only rate is integrated exactly */
    return model_outputs(inst);
}
