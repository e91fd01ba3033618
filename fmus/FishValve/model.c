/* FishValve physics: the 3/2 solenoid valve of one tail channel of the soft fish (PHYSICS.md
 * section 7). The spool connects the channel to the supply (open) or to the vent (closed).
 *
 * Why three FMUs (GasSource, FishValve x 2, FishBody) and mass flow as the coupling variable: the
 * three parts exchange only pressures, temperatures and mass flows, and none of them has an
 * algebraic relation across a boundary (the channel pressure is a state of the body, the supply
 * pressure one of the source, the flow an algebraic function of both). So a valve reads the
 * supply and channel pressures at the start of a communication step and publishes the flows it
 * computes from them; the body integrates its channel mass from mdot_in - mdot_vent and the source
 * its canister mass from the total draw, both over the same step with the same published values
 * (zero-order hold). Gas mass is therefore conserved exactly, to rounding, across the three FMUs
 * whatever the valve does. The explicit coupling is accurate because the fill time constant of a
 * 12 mL channel through a sub-millimetre nozzle (tens of ms) is far above the 1 ms step; near
 * equal pressures the flow ~ sqrt(dp) has an infinite slope, but the limit cycle it allows in an
 * explicit loop has an amplitude (gamma R T h Cd A sqrt(rho / 2) / V)^2 ~ 1e-5 Pa [derived].
 * The same valve model serves both channels (two instances): one physics, two sides.
 *
 * Spool: a command change takes effect after the dead time t_delay (commands are queued, so a
 * pulse shorter than the delay is still delivered, delayed); the spool then follows the commanded
 * end with a first-order lag tau_valve, integrated exactly (the solver's stiff rate -1/tau). The
 * supply nozzle's effective area is opening * Cd A_nozzle, the vent's (1 - opening) * Cd A_vent.
 *
 * Nozzle flow of an ideal gas from upstream (p_u, T_u) to downstream p_d, r = p_d / p_u
 * (isentropic flow to the throat, Saint-Venant-Wantzel) [derived]:
 *   choked,   r <= r_c: mdot = Cd A p_u sqrt(gamma / (R T_u)) (2 / (gamma + 1))^((gamma+1)/(2(gamma-1)))
 *   subsonic, r >  r_c: mdot = Cd A p_u sqrt(2 gamma / ((gamma - 1) R T_u) (r^(2/gamma) - r^((gamma+1)/gamma)))
 * with r_c = (2 / (gamma + 1))^(gamma / (gamma - 1)) = 0.5475 for CO2 (gamma 1.29). At r = r_c the
 * two expressions are equal (the subsonic one is maximal there), so the flow is continuous with a
 * continuous first derivative in r. Reverse pressure drop reverses the flow (upstream swapped). */
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

/* Signed mass flow from side 1 to side 2 [kg/s]: the higher pressure is upstream. */
static double nozzle_flow(double CdA, double p1, double T1, double p2, double T2, double gamma,
                          double R) {
    if (p1 >= p2) return forward_flow(CdA, p1, T1, p2, gamma, R);
    return -forward_flow(CdA, p2, T2, p1, gamma, R);
}

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
    const double gamma = V(inst, gamma), R = V(inst, R_gas), p_atm = V(inst, p_atm);
    const double x = s->y[OPENING];
    const double p_channel = p_atm + V(inst, p_channel);
    const double p_supply = V(inst, p_supply);
    const double CdA_in = x * V(inst, Cd_nozzle) * area(V(inst, d_nozzle));
    const double CdA_vent = (1.0 - x) * V(inst, Cd_vent) * area(V(inst, d_vent));
    V(inst, mdot_in) = nozzle_flow(CdA_in, p_supply, V(inst, T_supply), p_channel,
                                   V(inst, T_channel), gamma, R);
    V(inst, mdot_vent) = nozzle_flow(CdA_vent, p_channel, V(inst, T_channel), p_atm,
                                     V(inst, T_supply), gamma, R);
    V(inst, opening) = x;
    V(inst, choked) = p_supply > 0.0 && p_channel / p_supply <= critical_ratio(gamma);
    V(inst, critical_ratio) = critical_ratio(gamma);
    return fmi2OK;
}

fmi2Status model_initialize(Instance *inst, OdeSystem *ode) {
    State *s = (State *)inst->state;
    const int command = V(inst, open) != 0.0;
    if (V(inst, p_atm) + V(inst, p_channel) <= 0.0) {
        log_message(inst, fmi2Error, "input p_channel = %g Pa: absolute channel pressure not positive",
                    V(inst, p_channel));
        return fmi2Error;
    }
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
