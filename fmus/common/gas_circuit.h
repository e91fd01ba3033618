/* The closed gas circuit of one antagonistic channel pair of a fluidic elastomer actuator, shared
 * by the models that carry it (FeaSegment, ArmBody). Side i in {a, b} is cylinder chamber + tubing
 * + elastomer channel of volume
 *   V_i = A s_i(x) + V_dead + V_ch0 + sign_i G(g_i) theta + C_a g_i,  s_a = stroke - x, s_b = x,
 * sign_a = +1, sign_b = -1, g_i the gauge pressure and theta the bend angle the pair acts on.
 *
 * Vacuum [estimate]: a thin-walled channel below atmospheric pressure partially collapses, so its
 * bend sensitivity G(g) = dV/dtheta is G_a for g >= 0 and G_a (beta + (1 - beta) exp(g /
 * p_collapse)) for g < 0, beta = vacuum_factor. By virtual work the pair's torque is
 * H(g_a) - H(g_b), H(g) = int_0^g G(s) ds, and the channel walls store the membrane energy
 *   Psi = C_a g^2 / 2 + sign theta (g G(g) - H(g)).
 *
 * Gas: ideal gas with polytropic exponent n, p = R theta_s (m / V)^n with theta_s the adiabatic
 * invariant T (V / m)^(n - 1); n = 1 is isothermal (theta_s = T). The functions here are pure: no
 * instance, no state; a model keeps a GasCircuit with its parameters. */
#ifndef SOFTHIL_GAS_CIRCUIT_H
#define SOFTHIL_GAS_CIRCUIT_H

/* Parameters of one pair's circuit (SI units). */
typedef struct {
    double area;                      /* cylinder bore area [m^2] */
    double stroke;                    /* [m] */
    double V_dead, V_ch0;             /* dead volume and unbent channel volume per side [m^3] */
    double C_a;                       /* channel compliance [m^3/Pa] */
    double G_a;                       /* bend sensitivity under pressure [m^3/rad] */
    double vacuum_factor, p_collapse; /* beta [1] and the collapse's vacuum scale [Pa] */
    double p_atm;                     /* [Pa] */
    double R_gas;                     /* [J/(kg K)] */
    double n_poly;                    /* polytropic exponent [1] */
} GasCircuit;

/* A channel at gauge pressure g: its bend sensitivity G(g) = dV/dtheta [m^3/rad] and its torque
 * per unit sign H(g) [N m]. */
typedef struct {
    double G, H;
} Channel;

/* Both sides of a pair at one state. */
typedef struct {
    double g[2];        /* gauge pressures of a and b [Pa] */
    double V[2];        /* gas volumes [m^3] */
    Channel channel[2]; /* the channels at those pressures */
} GasState;

/* sign_i of the bend term: +1 for side a, -1 for side b */
extern const double GAS_SIGN[2];

/* The channel at gauge pressure g (G and H at the same g, as the energy balance needs). */
Channel gas_channel_at(const GasCircuit *c, double g);

/* Rigid part of a side's volume (without the bend and compliance terms) [m^3]. */
double gas_base_volume(const GasCircuit *c, double swept_length);

/* Length of the cylinder swept by side `side` (0: a, 1: b) at piston position x [m]. */
double gas_swept_length(const GasCircuit *c, double x, int side);

/* Gauge pressure of a side of gas mass m and invariant theta_s whose rigid volume is V0 and bend
 * term sign G(g) theta. Returns 0 if no physical root exists. */
int gas_pressure(const GasCircuit *c, double V0, double sign, double theta, double m,
                 double theta_s, double *gauge);

/* Both sides at piston position x and bend theta, masses m[2] and invariants theta_s[2]; 0 if a
 * side has no physical state. */
int gas_state(const GasCircuit *c, double x, double theta, const double m[2],
              const double theta_s[2], GasState *gas);

/* Torque of the pair on its bend angle, by virtual work [N m]. */
double gas_bending_torque(const GasState *gas);

/* Energy stored in the walls of side `side`'s channel, Psi above [J]. */
double gas_membrane_energy(const GasCircuit *c, const GasState *gas, int side, double theta);

/* The gas's free energy relative to the atmosphere of side `side` [J] (up to a constant):
 * -m R theta_s ln V + p_atm V isothermal, p V / (n - 1) + p_atm V polytropic. */
double gas_free_energy(const GasCircuit *c, const GasState *gas, int side, double m,
                       double theta_s);

#endif
