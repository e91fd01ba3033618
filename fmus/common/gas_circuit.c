/* The closed gas circuit of an antagonistic channel pair (see gas_circuit.h). */
#include "gas_circuit.h"

#include <math.h>

const double GAS_SIGN[2] = {+1.0, -1.0};

Channel gas_channel_at(const GasCircuit *c, double g) {
    const double beta = c->vacuum_factor, pc = c->p_collapse, G_a = c->G_a;
    Channel channel;
    if (g >= 0.0) {
        channel.G = G_a;
        channel.H = G_a * g;
    } else {
        const double em1 = expm1(g / pc);
        channel.G = G_a * (beta + (1.0 - beta) * (1.0 + em1));
        channel.H = G_a * (beta * g + (1.0 - beta) * pc * em1);
    }
    return channel;
}

/* The bend sensitivity G(g) and its slope dG/dg [m^3/(rad Pa)] from one exp: what the Newton
 * solves of the gas pressure need at every iteration. */
static double sensitivity_and_slope(const GasCircuit *c, double g, double *slope) {
    const double G_a = c->G_a, beta = c->vacuum_factor, pc = c->p_collapse;
    double e;
    if (g >= 0.0) {
        *slope = 0.0;
        return G_a;
    }
    e = exp(g / pc);
    *slope = G_a * (1.0 - beta) / pc * e;
    return G_a * (beta + (1.0 - beta) * e);
}

double gas_base_volume(const GasCircuit *c, double swept_length) {
    return c->area * swept_length + c->V_dead + c->V_ch0;
}

double gas_swept_length(const GasCircuit *c, double x, int side) {
    return side == 0 ? c->stroke - x : x;
}

/* The isothermal vacuum Newton stops once a step is below NEWTON_STEP [Pa]: it converges
 * quadratically, so the error left after that step is of order step^2 / p_collapse, under 1e-10 Pa
 * (measured against a 1e-9 Pa stop over the whole stroke and bend range: 3e-11 Pa), and it takes
 * one exp fewer per solve. */
#define NEWTON_STEP 1e-3

/* Solves ln(p_atm + g) + n ln V(g) = ln(R theta_s m^n), increasing in g (the models check that
 * at initialisation), by Newton steps kept inside p > 0, V > 0. */
int gas_pressure(const GasCircuit *c, double V0, double sign, double theta, double m,
                 double theta_s, double *gauge) {
    const double p_atm = c->p_atm, C = c->C_a, n = c->n_poly;
    double g, lo = -p_atm, target;
    int iteration;
    if (!(m > 0.0) || !(theta_s > 0.0)) return 0;
    if (n == 1.0) {
        /* isothermal: (p_atm + g) V(g) = m R T. Under pressure G = G_a and this is a quadratic
         * in g (stable form of the + root); under vacuum Newton from that root */
        const double mRT = m * c->R_gas * theta_s;
        const double V1 = V0 + sign * c->G_a * theta, B = C * p_atm + V1;
        const double c0 = p_atm * V1 - mRT, disc = B * B - 4.0 * C * c0;
        if (V1 > 0.0 && disc >= 0.0) {
            g = -2.0 * c0 / (B + sqrt(disc));
            if (g >= 0.0) {
                *gauge = g;
                return 1;
            }
            for (iteration = 0; iteration < 30; iteration++) {
                double dG;
                const double G = sensitivity_and_slope(c, g, &dG);
                const double p = p_atm + g, vol = V0 + sign * G * theta + C * g;
                const double dF = vol + p * (C + sign * dG * theta);
                double step;
                if (!(p > 0.0) || !(vol > 0.0) || !(dF > 0.0)) break;
                step = (p * vol - mRT) / dF;
                g -= step;
                if (fabs(step) <= NEWTON_STEP) {
                    *gauge = g < 0.0 ? g : 0.0;
                    return 1;
                }
            }
        }
    }
    target = log(c->R_gas * theta_s) + n * log(m);
    if (!isfinite(target)) return 0;
    /* start from the rigid solution at the channel's current sensitivity */
    {
        const double rigid = V0 + sign * c->G_a * theta;
        if (!(rigid > 0.0)) return 0;
        g = exp(target - n * log(rigid)) - p_atm;
    }
    for (iteration = 0; iteration < 60; iteration++) {
        double dG;
        const double G = sensitivity_and_slope(c, g, &dG);
        const double p = p_atm + g, vol = V0 + sign * G * theta + C * g;
        double f, df, next;
        if (!(p > 0.0) || !(vol > 0.0)) {
            g = 0.5 * (g + lo); /* back into the domain */
            continue;
        }
        f = log(p) + n * log(vol) - target;
        if (f < 0.0 && g > lo) lo = g;
        df = 1.0 / p + n * (C + sign * dG * theta) / vol;
        if (!(df > 0.0)) return 0;
        next = g - f / df;
        if (!(next > lo)) next = 0.5 * (g + lo);
        if (fabs(next - g) <= 1e-12 * p) {
            *gauge = next;
            return isfinite(next);
        }
        g = next;
    }
    return 0;
}

int gas_state(const GasCircuit *c, double x, double theta, const double m[2],
              const double theta_s[2], GasState *gas) {
    int side;
    for (side = 0; side < 2; side++) {
        const double V0 = gas_base_volume(c, gas_swept_length(c, x, side));
        if (!gas_pressure(c, V0, GAS_SIGN[side], theta, m[side], theta_s[side], &gas->g[side]))
            return 0;
        gas->channel[side] = gas_channel_at(c, gas->g[side]);
        gas->V[side] = V0 + GAS_SIGN[side] * gas->channel[side].G * theta + c->C_a * gas->g[side];
    }
    return 1;
}

double gas_bending_torque(const GasState *gas) { return gas->channel[0].H - gas->channel[1].H; }

double gas_membrane_energy(const GasCircuit *c, const GasState *gas, int side, double theta) {
    const double g = gas->g[side];
    return 0.5 * c->C_a * g * g +
           GAS_SIGN[side] * theta * (g * gas->channel[side].G - gas->channel[side].H);
}

double gas_free_energy(const GasCircuit *c, const GasState *gas, int side, double m,
                       double theta_s) {
    const double n = c->n_poly, p_atm = c->p_atm, vol = gas->V[side];
    return n == 1.0 ? -m * c->R_gas * theta_s * log(vol) + p_atm * vol
                    : (p_atm + gas->g[side]) * vol / (n - 1.0) + p_atm * vol;
}
