/* GasSource physics: the soft fish's on-board CO2 canister and its pressure regulator (README,
 * "The soft fish"). See FishValve/model.c for why the fish is three FMUs coupled by mass flow:
 * this one integrates its mass from the valves' published draws over each step (zero-order
 * hold), so the canister's loss equals what the channels gain plus what the vents release, to
 * rounding.
 *
 * Canister [estimate]: held at T_canister by the surrounding water (a draw of a few mg per
 * manoeuvre from 16 g cools it little). While the mass m exceeds m_sat = rho_vapour V the canister
 * holds liquid and vapour at the vapour pressure p_vapour. Below it only vapour is left, with
 *   p = rho R T / (1 + b rho),   rho = m / V,   b = (rho_vapour R T / p_vapour - 1) / rho_vapour,
 * a one-parameter correction of the ideal gas (b > 0: saturated CO2 vapour has a compressibility
 * factor of about 0.53 at 21 C) that is ideal at low density and meets p_vapour at saturation, so
 * the pressure is continuous and increasing in m [derived]. It tends to 0 with m: nothing is
 * singular when the canister runs down.
 *
 * Regulator [estimate]: ideal (no droop, no dynamics), p_supply = min(p_set, p_canister). Once the
 * canister falls below p_set the output flag `empty` is set and the supply pressure falls with the
 * canister's; the valves' flows then fall to zero as the supply approaches the channels' pressure,
 * so the mass stays positive. Usable mass: what can leave before the canister drops below p_set,
 * m - m_set with m_set = V p_set / (R T - b p_set) (the inverse of the vapour law). */
#include <math.h>

#include "glue.h"

enum { MASS, N_STATES };

typedef struct {
    double y[N_STATES]; /* canister mass [kg] */
} State;

size_t model_state_size(void) { return sizeof(State); }

/* b of the vapour law [m^3/kg] (see the header). */
static double vapour_correction(const Instance *inst) {
    const double rho_v = V(inst, rho_vapour);
    return (rho_v * V(inst, R_gas) * V(inst, T_canister) / V(inst, p_vapour) - 1.0) / rho_v;
}

/* Canister pressure at mass m [Pa abs]. */
static double canister_pressure(const Instance *inst, double m) {
    const double rho = m / V(inst, V_canister), rho_v = V(inst, rho_vapour);
    if (rho >= rho_v) return V(inst, p_vapour);
    return rho * V(inst, R_gas) * V(inst, T_canister) / (1.0 + vapour_correction(inst) * rho);
}

/* Mass at which the canister pressure equals p [kg] (p <= p_vapour). */
static double mass_at_pressure(const Instance *inst, double p) {
    return V(inst, V_canister) * p /
           (V(inst, R_gas) * V(inst, T_canister) - vapour_correction(inst) * p);
}

/* Liquid mass in a two-phase canister of mass m [kg]: m = rho_l V_l + rho_v (V - V_l). */
static double liquid_mass(const Instance *inst, double m) {
    const double rho_l = V(inst, rho_liquid), rho_v = V(inst, rho_vapour);
    const double V_l = (m - rho_v * V(inst, V_canister)) / (rho_l - rho_v);
    return V_l > 0.0 ? rho_l * V_l : 0.0;
}

int model_derivatives(const Instance *inst, const double y[], double dy[]) {
    (void)y;
    dy[MASS] = -(V(inst, mdot_a) + V(inst, mdot_b));
    return 1;
}

double model_time_to_event(const Instance *inst) {
    (void)inst;
    return INFINITY;
}

void model_discrete_update(Instance *inst) { (void)inst; }

void model_after_substep(Instance *inst, double dt) {
    (void)inst;
    (void)dt;
}

fmi2Status model_step_start(Instance *inst) {
    (void)inst;
    return fmi2OK;
}

fmi2Status model_outputs(Instance *inst) {
    const State *s = (const State *)inst->state;
    const double m = s->y[MASS], p_set = V(inst, p_set);
    double p;
    if (!(m > 0.0)) {
        log_message(inst, fmi2Error,
                    "canister mass %g kg is not positive: the inputs mdot_a, mdot_b drew more "
                    "than the canister held",
                    m);
        return fmi2Error;
    }
    p = canister_pressure(inst, m);
    V(inst, p_canister) = p;
    V(inst, p_supply) = p < p_set ? p : p_set;
    V(inst, T_supply) = V(inst, T_feed);
    V(inst, m_canister) = m;
    V(inst, m_liquid) = liquid_mass(inst, m);
    V(inst, m_drawn) = V(inst, m_initial) - m;
    {
        const double usable = m - mass_at_pressure(inst, p_set);
        V(inst, m_usable) = usable > 0.0 ? usable : 0.0;
    }
    V(inst, empty) = p < p_set;
    return fmi2OK;
}

fmi2Status model_initialize(Instance *inst, OdeSystem *ode) {
    State *s = (State *)inst->state;
    if (!(V(inst, rho_liquid) > V(inst, rho_vapour))) {
        log_message(inst, fmi2Error, "invalid parameters: rho_liquid = %g must exceed rho_vapour = %g",
                    V(inst, rho_liquid), V(inst, rho_vapour));
        return fmi2Error;
    }
    if (!(vapour_correction(inst) >= 0.0)) {
        log_message(inst, fmi2Error,
                    "invalid parameters: saturated vapour denser than an ideal gas at p_vapour "
                    "(rho_vapour R_gas T_canister = %g Pa < p_vapour = %g Pa)",
                    V(inst, rho_vapour) * V(inst, R_gas) * V(inst, T_canister), V(inst, p_vapour));
        return fmi2Error;
    }
    if (!(V(inst, p_set) < V(inst, p_vapour))) {
        log_message(inst, fmi2Error, "invalid parameter p_set = %g Pa: at or above p_vapour = %g Pa",
                    V(inst, p_set), V(inst, p_vapour));
        return fmi2Error;
    }
    if (V(inst, m_initial) > V(inst, rho_liquid) * V(inst, V_canister)) {
        log_message(inst, fmi2Error,
                    "invalid parameter m_initial = %g kg: more than the canister holds as liquid "
                    "(%g kg)",
                    V(inst, m_initial), V(inst, rho_liquid) * V(inst, V_canister));
        return fmi2Error;
    }
    if (!(V(inst, m_initial) > 0.0)) {
        log_message(inst, fmi2Error, "invalid parameter m_initial = %g kg: must be positive",
                    V(inst, m_initial));
        return fmi2Error;
    }
    s->y[MASS] = V(inst, m_initial);
    ode->n = N_STATES;
    ode->y = s->y;
    ode->max_substep = V(inst, substep);
    ode->stability_limit = INFINITY; /* the draw does not depend on the state */
    return model_outputs(inst);
}
