/* Environment physics: the planar world of an arm lying on a table (issue 12). Channel walls are
 * up to 2 polylines, objects up to 4 rigid disks; the arm's backbone is sampled at n_samples
 * points per segment (s = L k / n, k = 1..n; the base is clamped), each the centre of a capsule of
 * radius width / 2. Invariant: every force the environment applies is a penalty spring (elastic,
 * E_contact) plus terms whose power is never positive (E_dissipated), and the arm receives it only
 * as generalised torques work-conjugate to its bend angles.
 *
 * Kinematics: planar PCC exactly as controllers/kinematics.py (chord form, sinc(u/2) with its
 * series below |u/2| < 1e-6). Segment j with start pose (b_j, phi_j) puts the point at arc s at
 *   p = b_j + s g(u) (cos(phi_j + u/2), sin(phi_j + u/2)),  u = theta_j s / L_j,
 *   g(u) = sin(u/2) / (u/2).
 * Its Jacobian on the bend angles theta_i = kappa_i L_i (analytic): dp/dtheta_i = 0 for i > j;
 * for i = j, (s / L_j) dl/du of the local chord l; for i < j, d(b_j)/dtheta_i + z x (p - e_i)
 * collected along the chain (bending segment i turns everything beyond its end about that end
 * and moves the end).
 *
 * Torque (sign convention): tau_ext_i = sum_p F_p . dp/dtheta_i over the points p at or beyond the
 * start of segment i, F_p the force of the environment on the arm at p. A positive tau_ext_i does
 * positive work on a positive bend rate: it is FeaSegment's tau_ext (I theta'' + ... = ... +
 * tau_ext), and for the elastic part tau_i = -dE_contact/dtheta_i (virtual work; tested by finite
 * differences).
 *
 * Contact at a point p of capsule radius r: against a wall polyline the closest edge point c
 * (distance d, min over the edges, so a vertex is not counted twice), depth delta = r - d,
 * normal n = (p - c) / d; against a disk of radius R at o, delta = r + R - d, n = (p - o) / d.
 * Normal force (Hunt and Crossley 1975) F_n = max(0, delta (k + c_d delta')), delta' = -n . v_rel:
 * continuous where a contact opens or closes (a Kelvin-Voigt k delta + c delta' jumps there, and
 * the implicit coupling's Newton iteration stalls on that kink), it never pulls, and its
 * dissipated power (F_n - k delta) delta' is c_d delta delta'^2 >= 0, or -k delta delta' >= 0 in
 * the clamped branch (separation faster than k / c_d). Coulomb friction, regularised:
 * F_t = -mu F_n tanh(|v_t| / v_slip) v_t / |v_t|, power -F_t . v_t >= 0. Table friction on the
 * arm: each point carries mass_j / n_samples, force -mu_table m_p g tanh(|v| / v_slip) v / |v|.
 * Walls are two-sided lines: a point deeper than its radius tunnels (penetrations stay below
 * 1 mm in the tests, far below the 10 mm radius).
 *
 * Coupling (why the torque is solved implicitly): the arm lies on a table, its segments are
 * overdamped (bend damping d ~ 6e-3 N m s/rad, inertia m L^2 / 20 ~ 5e-6 kg m^2), and a penalty
 * contact at the tip of a six-segment arm has a generalised stiffness k |J|^2 ~ 1000 N/m *
 * 0.33 m^2 = 330 N m/rad. Held over a 1 ms co-simulation step, an explicit torque gains
 * k |J|^2 h / d ~ 50 per step: unstable by far. The environment therefore predicts the arm's
 * configuration when the torque will act, q = theta_n + H theta_dot_n + H m (tau - tau_now),
 * H = (1 + coupling_delay) h, m = arm_mobility (~1/d), and solves tau = G(q(tau)) by Newton on
 * the contact's stiffness, damping and friction tangents (a 7 x 7 system). For a linear contact
 * tau = -K theta on an inertia-free arm this makes the error shrink by 1 / (1 + m K H) per step:
 * unconditionally stable, and at rest (theta_dot = 0, tau = tau_now) it is exactly
 * tau = G(theta): the equilibrium is the physical one. arm_mobility = 0 is the explicit coupling.
 * Measured with FeaSegments (six segments pressed into a wall, Jacobi, 1 ms): stable for
 * arm_mobility from 100 to 2000 rad/(N m s) (1/d = 167); 50 (assuming more damping than the arm
 * has) diverges, and 20000 lets the contact sink to 10 mm. Set it to 1 / d_bend.
 *
 * Energy (outputs): the arm is the only source. W_arm is the work of tau_ext on the arm
 * (sum tau . delta theta over the bend angles received, exact for a torque held over each step as
 * FeaSegment holds it), W_objects that of the contact forces on the objects (W_contact is their
 * sum), E_contact the elastic energy of every penetration, E_kinetic the objects' kinetic energy,
 * E_dissipated contact damping, contact friction and table friction (arm and objects). The
 * environment never adds energy: -W_arm = dE_contact + dE_kinetic + E_dissipated with
 * E_dissipated non-decreasing, to the discretisation of the steps and substeps and to what the
 * coupling's prediction misses (see Passivity).
 *
 * Passivity: the prediction is exact only for an inertia-free arm and the coupling the
 * parameters state; what it misses (the segments' inertia m L^2 / 20 over a 1 ms step, the Jacobi
 * delay) can return a little more energy than a contact holds, for example at an impact. A
 * passivity observer and controller (Hannaford and Ryu 2002, see passivity_damping) watches the
 * energy balance at the interface, which the environment knows exactly, and damps the deficit
 * away in the next steps. Measured (six segments into a wall, Jacobi): with the default friction
 * the net work on the arm never turns positive; frictionless, an impact's rebound hands the arm
 * at most 1.2 % of the impact's elastic energy for a few steps before the controller takes it
 * back.
 *
 * Objects in the coupling (a known artefact): the arm is predicted H ahead, the objects are held
 * where they are, so a carried object is also an obstacle the predicted arm runs into: a drag of
 * about k H v per contact at the hand's speed v, which vanishes at rest (measured: 0.02 N m on
 * the base of an arm creeping at 3 cm/s with a 5 g object, most of a segment's torque; the arm
 * gets there, slower). Four cures were tried and each was unstable: predicting the objects at
 * their velocity (a squeezed object's velocity answers the contact within a step, loop gain
 * ~ k H h / m per contact, about 1 for 5 g), at their velocity low-passed over 20 ms, or rigidly
 * with the hand when both fingers hold them (the object's inertia then reaches the arm through
 * its lag only, an explicit coupling of gain k |J|^2 h / d ~ 20 at the base), and leaving the
 * objects' contact explicit (closing fingers hit an object with 30 N). The consistent cure
 * solves the objects' velocities in the same implicit system as the arm's torques.
 *
 * Objects: disks (x, y, yaw) pushed by the arm and stopped by the walls and by table friction
 * (exact Coulomb: a velocity update that may stop but never reverse the motion, torque limit
 * 2/3 mu m g R for uniform pressure), integrated by semi-implicit Euler in substeps (stable below
 * 1 / sqrt(2 k / m_min), checked at initialisation; their contacts' damping is capped at what a
 * substep resolves, see object_damping, so that an object started deep in the arm leaves with
 * at most the overlap's elastic energy). During a step the arm moves along
 * theta_n + theta_dot_n t for them. Neglected: object-object contact; the arm's reaction to
 * the objects uses their poses at the step's end (an O(h) mismatch of action and reaction).
 *
 * Gripper (gripper = 1): a finger pair at the tip (robots/planar_arm/controller/gripper.py, see fingers()) adds one
 * degree of freedom after the segments, the fingers' common bend angle: gripper_theta in,
 * gripper_tau_ext out, solved in the same implicit coupling. An object is held only by the
 * contact forces of both fingers enclosing it (finger_force_left/right), never attached.
 *
 * Tipping (object_upright, object_tilt): a monitor of whether the pushes would tip an upright
 * cylinder over, not fed back into the planar motion (see tip_over()).
 *
 * Table friction [estimate]: an elastomer's mu ~ 0.3 gives a Coulomb torque mu m g L / 2 per
 * segment for its own mass only. Acting on every backbone point, friction of the segments beyond
 * also resists a bend: the torque on segment i is mu g sum_p m_p |dp/dtheta_i|, 0.27 mu N m on
 * the base of a straight six-segment arm (0.03 kg, 0.06 m per segment), 0.080 N m at mu = 0.3:
 * about three times the segment's full-stroke torque (G_a 40 kPa ~ 0.03 N m), so such an arm could
 * not bend its base. The default mu_table = 0.02 (a low-friction support) gives 5.4e-3 N m on the
 * base and 6e-5 N m on the tip (m g L / 6 mu), the order of a segment's friction dead band.
 *
 * What the arm neglects: each FeaSegment integrates its own bend angle
 * with its own inertia m L^2 / 20 about its base, so the inertia of the segments beyond it (the
 * full PCC mass matrix M_ij = sum_p m_p dp/dtheta_i . dp/dtheta_j) is absent, and so is the
 * inertial coupling between segments. Size, for a straight six-segment arm (computed in
 * tests/test_environment.py from controllers/kinematics.py): M_11 = 6.1e-3 kg m^2 against the
 * modelled 5.4e-6 (M_22 3.4e-3, M_33 1.6e-3, M_44 5.9e-4, M_55 1.3e-4, M_66 6e-6 = the modelled
 * value). Against the bending damping d = 6e-3 N m s/rad the base's inertial time constant
 * M_11 / d is 1.0 s: the neglect is small only for motions slower than ~1 rad/s of bandwidth at
 * the base (inertial torque M_11 theta'' below d theta' for frequencies below d / M_11 ~ 1 rad/s;
 * at the tip segments it is small up to 45 rad/s). It cannot be supplied through tau_ext (the
 * missing inertia is up to 1100 times the modelled one: an explicit inertial torque from
 * estimated accelerations would be unstable); a faithful fast arm needs a multibody arm FMU, as
 * the spatial arm has. Also neglected: the table's drag is Coulomb only (no viscous film). */
#include <math.h>
#include <string.h>

#include "glue.h"

#define MAX_SEGMENTS 7
#define MAX_DOF (MAX_SEGMENTS + 1) /* the segments' bend angles and the fingers' */
#define MAX_SAMPLES 16
#define MAX_POINTS ((MAX_SEGMENTS + 2) * MAX_SAMPLES) /* the segments' and two fingers' */
#define MAX_WALLS 2
#define MAX_OBJECTS 4
#define NEWTON_ITERATIONS 20
#define MAX_HALVINGS 12
#define PASSIVITY_MAX_GAIN 100.0 /* largest passivity damping, in units of 1 / arm_mobility */
#define NEWTON_TOLERANCE 1e-12 /* |tau - G|_1 [N m] */
#define SMALL_HALF_ANGLE 1e-6

/* indexed family member i (0-based) of the variables declared with `count` */
#define VI(inst, family, i) ((inst)->v[VR_##family##_1 + (i)])

enum { OX, OY, OYAW, OVX, OVY, OW, N_OBJECT_STATES };

typedef struct {
    double object[MAX_OBJECTS][N_OBJECT_STATES];
    /* per degree of freedom: the segments' bend angles, then the fingers' if there is a gripper */
    double theta[MAX_DOF];      /* bend angles received at this step's start [rad] */
    double theta_dot[MAX_DOF];  /* bend rates received [rad/s] */
    double theta_prev[MAX_DOF]; /* bend angles of the previous step [rad] */
    double tau_now[MAX_DOF];    /* torque acting on the arm during this step [N m] */
    double tau_next[MAX_DOF];   /* torque output, acting after this step if delayed [N m] */
    double tilt[MAX_OBJECTS][2]; /* each object's tilt about its base's edge [rad], its rate */
    int toppled[MAX_OBJECTS];
    int have_prev;
    double t_step;     /* time since this step's start [s] */
    double E_diss;     /* [J] */
    double W_arm;      /* [J] */
    double W_objects;  /* [J] */
    double impulse;    /* [N s] */
    double beta;       /* passivity damping of this step [N m s/rad] */
} State;

size_t model_state_size(void) { return sizeof(State); }

/* ---------------------------------------------------------------- kinematics */

typedef struct {
    int n;                         /* points in use */
    int segment[MAX_POINTS];       /* the degree of freedom owning each point (a finger's: the
                                      gripper's); the point moves with it and every one before */
    int finger[MAX_POINTS];        /* 0 on the arm, 1 on the left finger, 2 on the right */
    double radius[MAX_POINTS];     /* capsule radius [m] */
    double mass[MAX_POINTS];       /* mass the point carries for table friction [kg] */
    double p[MAX_POINTS][2];       /* positions [m] */
    double J[MAX_POINTS][MAX_DOF][2]; /* dp/dtheta_i [m/rad] */
} Backbone;

static int n_segments(const Instance *inst) { return (int)V(inst, n_segments); }

/* degrees of freedom: the segments' bend angles, then the fingers' (one angle, both fingers) */
static int n_dof(const Instance *inst) { return n_segments(inst) + (V(inst, gripper) != 0.0); }

/* g(u) = sin(u/2) / (u/2) and dg/du, series below SMALL_HALF_ANGLE as in kinematics.py */
static void chord_factor(double u, double *g, double *dg) {
    const double x = 0.5 * u;
    if (fabs(x) < SMALL_HALF_ANGLE) {
        *g = 1.0 - x * x / 6.0;
        *dg = 0.5 * (-x / 3.0);
    } else {
        *g = sin(x) / x;
        *dg = 0.5 * (x * cos(x) - sin(x)) / (x * x);
    }
}

/* The two fingers at the tip pose (b, phi) of the arm, appended to bb: each an arc of length L_f
 * from a root offset +-r0 across the axis, the left finger curving right (towards the axis) by
 * the bend angle theta_g and the right one mirrored, exactly as robots/planar_arm/controller/gripper.py. A point
 * l from the tip moves with segment i < ns by d(tip)/dtheta_i + z x l, and with theta_g by its
 * own arc's derivative. */
static void fingers(const Instance *inst, double theta_g, const double b[2], double phi,
                    const double db[][2], Backbone *bb) {
    const int ns = n_segments(inst), nk = (int)V(inst, n_samples);
    const double Lf = V(inst, finger_length), r0 = V(inst, finger_root_offset);
    const double nrm[2] = {-sin(phi), cos(phi)};
    int side, k, i;
    for (side = 0; side < 2; side++) {
        const double sign = side == 0 ? 1.0 : -1.0, curl = -sign; /* du / dtheta_g * L_f / s */
        for (k = 1; k <= nk; k++) {
            const double s = Lf * k / nk, u = curl * theta_g * s / Lf;
            const double c = cos(phi + 0.5 * u), sn = sin(phi + 0.5 * u);
            double g, dg, l[2];
            const int q = bb->n++;
            chord_factor(u, &g, &dg);
            l[0] = sign * r0 * nrm[0] + s * g * c;
            l[1] = sign * r0 * nrm[1] + s * g * sn;
            bb->segment[q] = ns;
            bb->finger[q] = side + 1;
            bb->radius[q] = 0.5 * V(inst, finger_width);
            bb->mass[q] = V(inst, finger_mass) / nk;
            bb->p[q][0] = b[0] + l[0];
            bb->p[q][1] = b[1] + l[1];
            for (i = 0; i < MAX_DOF; i++) {
                if (i < ns) {
                    bb->J[q][i][0] = db[i][0] - l[1];
                    bb->J[q][i][1] = db[i][1] + l[0];
                } else if (i == ns) {
                    bb->J[q][i][0] = curl * (s / Lf) * s * (dg * c - 0.5 * g * sn);
                    bb->J[q][i][1] = curl * (s / Lf) * s * (dg * sn + 0.5 * g * c);
                } else {
                    bb->J[q][i][0] = bb->J[q][i][1] = 0.0;
                }
            }
        }
    }
}

/* Sample points and their Jacobians at bend angles theta. */
static void backbone(const Instance *inst, const double theta[], Backbone *bb) {
    const int ns = n_segments(inst), nk = (int)V(inst, n_samples);
    double b[2] = {V(inst, base_x), V(inst, base_y)}, phi = V(inst, base_heading);
    double db[MAX_DOF][2]; /* d(segment start)/dtheta_i for i < j */
    int i, j, k;
    memset(db, 0, sizeof db);
    bb->n = 0;
    for (j = 0; j < ns; j++) {
        const double L = VI(inst, length, j);
        double end_l[2] = {0.0, 0.0}, end_dl[2] = {0.0, 0.0};
        for (k = 1; k <= nk; k++) {
            const double s = L * k / nk, u = theta[j] * s / L;
            const double c = cos(phi + 0.5 * u), sn = sin(phi + 0.5 * u);
            double g, dg, l[2], dl[2];
            const int q = bb->n++;
            chord_factor(u, &g, &dg);
            l[0] = s * g * c;
            l[1] = s * g * sn;
            /* d l / d theta_j = (s / L) d l / du */
            dl[0] = (s / L) * s * (dg * c - 0.5 * g * sn);
            dl[1] = (s / L) * s * (dg * sn + 0.5 * g * c);
            bb->segment[q] = j;
            bb->finger[q] = 0;
            bb->radius[q] = 0.5 * VI(inst, width, j);
            bb->mass[q] = VI(inst, mass, j) / nk;
            bb->p[q][0] = b[0] + l[0];
            bb->p[q][1] = b[1] + l[1];
            for (i = 0; i < MAX_DOF; i++) {
                if (i < j) { /* rotation of the local chord about the segment's start + start */
                    bb->J[q][i][0] = db[i][0] - l[1];
                    bb->J[q][i][1] = db[i][1] + l[0];
                } else if (i == j) {
                    bb->J[q][i][0] = dl[0];
                    bb->J[q][i][1] = dl[1];
                } else {
                    bb->J[q][i][0] = bb->J[q][i][1] = 0.0;
                }
            }
            if (k == nk) {
                end_l[0] = l[0], end_l[1] = l[1], end_dl[0] = dl[0], end_dl[1] = dl[1];
            }
        }
        for (i = 0; i < j; i++) {
            db[i][0] -= end_l[1];
            db[i][1] += end_l[0];
        }
        db[j][0] = end_dl[0];
        db[j][1] = end_dl[1];
        b[0] += end_l[0];
        b[1] += end_l[1];
        phi += theta[j];
    }
    if (V(inst, gripper) != 0.0) fingers(inst, theta[ns], b, phi, (const double(*)[2])db, bb);
}

/* ---------------------------------------------------------------- geometry */

static int wall_vertices(const Instance *inst, int w) {
    const int n = (int)(w == 0 ? V(inst, wall1_n) : V(inst, wall2_n));
    return w < (int)V(inst, n_walls) ? n : 0;
}

static void wall_vertex(const Instance *inst, int w, int k, double v[2]) {
    v[0] = w == 0 ? VI(inst, wall1_x, k) : VI(inst, wall2_x, k);
    v[1] = w == 0 ? VI(inst, wall1_y, k) : VI(inst, wall2_y, k);
}

/* Distance from p to wall polyline w and the unit normal from the closest point to p; returns 0
 * if the wall has no edge. A point on the line takes the edge's left normal. */
static int wall_distance(const Instance *inst, int w, const double p[2], double *distance,
                         double normal[2]) {
    const int n = wall_vertices(inst, w);
    double best2 = INFINITY, best_r[2] = {0.0, 0.0}, best_e[2] = {1.0, 0.0}, d;
    int k;
    for (k = 0; k + 1 < n; k++) {
        double a[2], b[2], e[2], t, len2, r[2], d2;
        wall_vertex(inst, w, k, a);
        wall_vertex(inst, w, k + 1, b);
        e[0] = b[0] - a[0];
        e[1] = b[1] - a[1];
        len2 = e[0] * e[0] + e[1] * e[1];
        t = len2 > 0.0 ? ((p[0] - a[0]) * e[0] + (p[1] - a[1]) * e[1]) / len2 : 0.0;
        t = t < 0.0 ? 0.0 : (t > 1.0 ? 1.0 : t);
        r[0] = p[0] - (a[0] + t * e[0]);
        r[1] = p[1] - (a[1] + t * e[1]);
        d2 = r[0] * r[0] + r[1] * r[1]; /* squared: one square root per wall, not per edge */
        if (d2 < best2) {
            best2 = d2;
            best_r[0] = r[0], best_r[1] = r[1];
            if (len2 > 0.0) best_e[0] = e[0], best_e[1] = e[1];
        }
    }
    d = sqrt(best2);
    *distance = d;
    if (d > 1e-12) {
        normal[0] = best_r[0] / d, normal[1] = best_r[1] / d;
    } else { /* on the line: the edge's left normal */
        const double le = hypot(best_e[0], best_e[1]);
        normal[0] = -best_e[1] / le, normal[1] = best_e[0] / le;
    }
    return n >= 2;
}

/* ---------------------------------------------------------------- contact law */

typedef struct {
    double F[2];        /* force on the first body (arm point or object) [N] */
    double normal_force;
    double elastic;     /* k delta^2 / 2 [J] */
    double dissipation; /* power dissipated [W], >= 0 */
    double K[2][2];     /* d(-F)/d(position): normal stiffness k n n^T [N/m] */
    double C[2][2];     /* d(-F)/d(velocity): damping and friction tangent [N s/m] */
} Contact;

/* Penalty contact of depth delta > 0 along unit normal n (pointing to the first body) at
 * relative velocity v of the first body against the second, friction coefficient mu, Hunt-Crossley
 * damping c (d_contact, or less for an object: see object_damping). */
static void contact_law(const Instance *inst, double delta, const double n[2], const double v[2],
                        double mu, double c, Contact *out) {
    const double k = V(inst, k_contact), eps = V(inst, v_slip);
    const double rate = -(n[0] * v[0] + n[1] * v[1]);
    double Fn = delta * (k + c * rate), vt[2], speed, fric = 0.0, slope = 0.0;
    int a, b;
    if (Fn < 0.0) Fn = 0.0;
    vt[0] = v[0] + rate * n[0];
    vt[1] = v[1] + rate * n[1];
    speed = hypot(vt[0], vt[1]);
    out->F[0] = Fn * n[0];
    out->F[1] = Fn * n[1];
    if (mu > 0.0) {
        const double sech = 1.0 / cosh(speed / eps);
        fric = mu * Fn * tanh(speed / eps);
        if (speed > 0.0) {
            out->F[0] -= fric * vt[0] / speed;
            out->F[1] -= fric * vt[1] / speed;
        }
        slope = mu * Fn / eps * sech * sech; /* d(friction)/d(sliding speed) */
    }
    out->normal_force = Fn;
    out->elastic = 0.5 * k * delta * delta;
    out->dissipation = (Fn - k * delta) * rate + fric * speed;
    for (a = 0; a < 2; a++)
        for (b = 0; b < 2; b++) {
            const double nn = n[a] * n[b], tt = (a == b ? 1.0 : 0.0) - nn;
            out->K[a][b] = Fn > 0.0 ? (k + c * rate) * nn : 0.0;
            out->C[a][b] = (Fn > 0.0 ? c * delta * nn : 0.0) + slope * tt;
        }
}

/* ---------------------------------------------------------------- forces on the arm */

typedef struct {
    double tau[MAX_DOF];
    double A[MAX_DOF][MAX_DOF]; /* sum J^T (H K + C) J: d(-tau)/d(rate) */
    double penetration[MAX_DOF];
    double force[MAX_DOF][2];
    double finger_force[2][2]; /* each finger's resultant contact force [N] */
    double elastic, dissipation, force_sum;
} ArmForces;

static void add_point_force(ArmForces *out, const Backbone *bb, int q, const double F[2],
                            const double K[2][2], const double C[2][2], double H) {
    const int last = bb->segment[q];
    double M[2][2];
    int i, j, a, b;
    for (i = 0; i <= last; i++) out->tau[i] += F[0] * bb->J[q][i][0] + F[1] * bb->J[q][i][1];
    /* A_ij += sum_ab (J_ia (H K_ab + C_ab)) J_jb, its factors formed once (the same doubles) */
    for (a = 0; a < 2; a++)
        for (b = 0; b < 2; b++) M[a][b] = H * K[a][b] + C[a][b];
    for (i = 0; i <= last; i++) {
        double row[2][2];
        for (a = 0; a < 2; a++)
            for (b = 0; b < 2; b++) row[a][b] = bb->J[q][i][a] * M[a][b];
        for (j = 0; j <= last; j++)
            for (a = 0; a < 2; a++)
                for (b = 0; b < 2; b++) out->A[i][j] += row[a][b] * bb->J[q][j][b];
    }
}

/* Adds a contact force at point q to its segment's (or finger's) resultant. */
static void add_resultant(ArmForces *out, const Backbone *bb, int q, const double F[2]) {
    out->force[bb->segment[q]][0] += F[0];
    out->force[bb->segment[q]][1] += F[1];
    if (bb->finger[q]) {
        out->finger_force[bb->finger[q] - 1][0] += F[0];
        out->finger_force[bb->finger[q] - 1][1] += F[1];
    }
}

/* Forces of walls, objects and table on the arm at bend angles q and rates rate; H weighs the
 * stiffness in the Newton matrix A. */
static void arm_forces(const Instance *inst, const State *s, const double q[],
                       const double rate[], double H, ArmForces *out) {
    const int ns = n_dof(inst);
    Backbone bb;
    int p, i, w, o;
    memset(out, 0, sizeof *out);
    backbone(inst, q, &bb);
    for (p = 0; p < bb.n; p++) {
        const int seg = bb.segment[p];
        const double r = bb.radius[p];
        double v[2] = {0.0, 0.0};
        for (i = 0; i < ns; i++) {
            v[0] += bb.J[p][i][0] * rate[i];
            v[1] += bb.J[p][i][1] * rate[i];
        }
        for (w = 0; w < MAX_WALLS; w++) {
            double d, n[2];
            Contact ct;
            if (!wall_distance(inst, w, bb.p[p], &d, n) || d >= r) continue;
            contact_law(inst, r - d, n, v, V(inst, mu_arm), V(inst, d_contact), &ct);
            add_point_force(out, &bb, p, ct.F, ct.K, ct.C, H);
            add_resultant(out, &bb, p, ct.F);
            if (r - d > out->penetration[seg]) out->penetration[seg] = r - d;
            out->elastic += ct.elastic;
            out->dissipation += ct.dissipation;
            out->force_sum += hypot(ct.F[0], ct.F[1]);
        }
        for (o = 0; o < (int)V(inst, n_objects); o++) {
            const double *ob = s->object[o], R = VI(inst, object_radius, o);
            double rel[2] = {bb.p[p][0] - ob[OX], bb.p[p][1] - ob[OY]}, d = hypot(rel[0], rel[1]);
            double n[2], vrel[2];
            Contact ct;
            if (d >= r + R || !(d > 0.0)) continue;
            n[0] = rel[0] / d, n[1] = rel[1] / d;
            /* the object's surface point R n moves at v_o + omega z x (R n) */
            vrel[0] = v[0] - (ob[OVX] - ob[OW] * R * n[1]);
            vrel[1] = v[1] - (ob[OVY] + ob[OW] * R * n[0]);
            contact_law(inst, r + R - d, n, vrel, V(inst, mu_arm), V(inst, d_contact), &ct);
            add_point_force(out, &bb, p, ct.F, ct.K, ct.C, H);
            add_resultant(out, &bb, p, ct.F);
            if (r + R - d > out->penetration[seg]) out->penetration[seg] = r + R - d;
            out->elastic += ct.elastic;
            /* its dissipation and impulse are counted in the objects' substeps (finer) */
        }
        { /* table friction of this point's share of the segment's mass */
            const double speed = hypot(v[0], v[1]), eps = V(inst, v_slip);
            const double weight = bb.mass[p] * V(inst, gravity);
            const double limit = V(inst, mu_table) * weight;
            const double Z[2][2] = {{0.0, 0.0}, {0.0, 0.0}};
            double F[2] = {0.0, 0.0}, C[2][2] = {{limit / eps, 0.0}, {0.0, limit / eps}};
            if (speed > 0.0) {
                /* the exact tangent of F = -f(|v|) v / |v|: f' along v, f / |v| across it */
                const double f = limit * tanh(speed / eps), sech = 1.0 / cosh(speed / eps);
                const double along = limit / eps * sech * sech, across = f / speed;
                int a, b;
                F[0] = -f * v[0] / speed;
                F[1] = -f * v[1] / speed;
                out->dissipation += f * speed;
                for (a = 0; a < 2; a++)
                    for (b = 0; b < 2; b++) {
                        const double vv = v[a] * v[b] / (speed * speed);
                        C[a][b] = along * vv + across * ((a == b ? 1.0 : 0.0) - vv);
                    }
            }
            add_point_force(out, &bb, p, F, Z, C, H);
        }
    }
}

/* Solves A x = b (n x n, A = I + m A' is diagonally dominant enough in practice: partial
 * pivoting anyway). Returns 0 if singular. */
static int solve_linear(int n, double A[MAX_DOF][MAX_DOF], double b[]) {
    int i, j, k;
    for (k = 0; k < n; k++) {
        int pivot = k;
        for (i = k + 1; i < n; i++)
            if (fabs(A[i][k]) > fabs(A[pivot][k])) pivot = i;
        if (!(fabs(A[pivot][k]) > 1e-300)) return 0;
        if (pivot != k) {
            double t;
            for (j = 0; j < n; j++) t = A[k][j], A[k][j] = A[pivot][j], A[pivot][j] = t;
            t = b[k], b[k] = b[pivot], b[pivot] = t;
        }
        for (i = k + 1; i < n; i++) {
            const double f = A[i][k] / A[k][k];
            for (j = k; j < n; j++) A[i][j] -= f * A[k][j];
            b[i] -= f * b[k];
        }
    }
    for (k = n - 1; k >= 0; k--) {
        for (j = k + 1; j < n; j++) b[k] -= A[k][j] * b[j];
        b[k] /= A[k][k];
    }
    return 1;
}

/* Residual tau - G(q(tau)) of the implicit coupling and the forces at q(tau); returns |.|_1. */
static double coupling_residual(const Instance *inst, const State *s, double H, const double tau[],
                                double residual[], ArmForces *out) {
    const int ns = n_dof(inst);
    const double m = V(inst, arm_mobility);
    double q[MAX_DOF] = {0.0}, rate[MAX_DOF] = {0.0}, size = 0.0;
    int i;
    for (i = 0; i < ns; i++) {
        rate[i] = s->theta_dot[i] + m * (tau[i] - s->tau_now[i]);
        q[i] = s->theta[i] + H * rate[i];
    }
    arm_forces(inst, s, q, rate, H, out);
    for (i = 0; i < ns; i++) { /* the passivity controller's damping (see the header) */
        out->tau[i] -= s->beta * rate[i];
        out->A[i][i] += s->beta;
        out->dissipation += s->beta * rate[i] * rate[i];
    }
    for (i = 0; i < ns; i++) {
        residual[i] = tau[i] - out->tau[i];
        size += fabs(residual[i]);
    }
    return size;
}

/* A damped Newton step from tau with the Newton matrix I + m A: the full step, halved until the
 * residual falls. Returns 1 and updates tau, residual, size and out if it found a descent. */
static int newton_step(const Instance *inst, const State *s, double H,
                       const double A[MAX_DOF][MAX_DOF], double tau[],
                       double residual[], double *size, ArmForces *out) {
    const int ns = n_dof(inst);
    const double m = V(inst, arm_mobility);
    double M[MAX_DOF][MAX_DOF], step[MAX_DOF], trial[MAX_DOF];
    double trial_residual[MAX_DOF], fraction = 1.0;
    ArmForces trial_out;
    int i, j, halvings;
    for (i = 0; i < ns; i++) {
        step[i] = -residual[i];
        for (j = 0; j < ns; j++) M[i][j] = (i == j ? 1.0 : 0.0) + m * A[i][j];
    }
    if (!solve_linear(ns, M, step)) return 0;
    for (halvings = 0; halvings < MAX_HALVINGS; halvings++, fraction *= 0.5) {
        double trial_size;
        for (i = 0; i < ns; i++) trial[i] = tau[i] + fraction * step[i];
        trial_size = coupling_residual(inst, s, H, trial, trial_residual, &trial_out);
        if (trial_size < *size) {
            for (i = 0; i < ns; i++) tau[i] = trial[i], residual[i] = trial_residual[i];
            *out = trial_out;
            *size = trial_size;
            return 1;
        }
    }
    return 0;
}

/* The torque for the arm, solved against its predicted response over the horizon H (see the
 * header): tau = G(theta + H theta_dot + H m (tau - tau_now)). The contact is piecewise smooth
 * where a contact opens or closes), so Newton is damped. Fills `out` at the torque found;
 * returns the residual left |tau - G|_1 [N m] (coupling_residual). */
static double solve_arm_torque(const Instance *inst, const State *s, double H, double tau[],
                               ArmForces *out) {
    const int ns = n_dof(inst);
    double residual[MAX_DOF], size;
    int i, it;
    for (i = 0; i < MAX_DOF; i++) tau[i] = i < ns ? s->tau_now[i] : 0.0;
    size = coupling_residual(inst, s, H, tau, residual, out);
    if (V(inst, arm_mobility) == 0.0) { /* explicit: the forces at theta + H theta_dot */
        for (i = 0; i < ns; i++) tau[i] = out->tau[i];
        return 0.0;
    }
    for (it = 0; it < NEWTON_ITERATIONS && size > NEWTON_TOLERANCE; it++) {
        if (!newton_step(inst, s, H, (const double(*)[MAX_DOF])out->A, tau, residual, &size,
                         out))
            break; /* no descent: keep the best torque found */
    }
    return size;
}

/* ---------------------------------------------------------------- objects */

/* The Hunt-Crossley damping coefficient of object o's contacts over a substep dt [N s/m^2]:
 * d_contact, reduced where the contacts' summed damping sum_p d_contact delta_p would exceed
 * m / dt. The objects' substeps are explicit in the contact force, and an explicit damper b
 * multiplies the normal approach speed by 1 - b dt / m per substep: beyond b dt / m = 1 it
 * reverses the approach into a separation, and since the contact never pulls (the force is
 * clamped at 0 while separating), each reversal is kept: an object placed 20 mm deep in a
 * straight arm (6 contacts of 100 N s/m, 5 g, dt 1e-4 s: b dt / m = 12) left at 700 m/s from
 * 0.15 J of penalty energy. Capped at m / dt, a substep stops the approach at most: the damper
 * only takes energy. Contacts as shallow as contact normally is (below m / (dt d_contact n),
 * 10 mm for 5 g and one contact) keep d_contact. The arm's side of the same contacts keeps
 * d_contact: its implicit solve is stable with any damping. */
static double object_damping(const Instance *inst, const State *s, int o, const Backbone *bb,
                             double dt) {
    const double *ob = s->object[o], R = VI(inst, object_radius, o);
    const double c = V(inst, d_contact), limit = VI(inst, object_mass, o) / dt;
    double depth = 0.0, d, n[2];
    int p, w;
    for (p = 0; p < bb->n; p++) {
        d = hypot(bb->p[p][0] - ob[OX], bb->p[p][1] - ob[OY]);
        if (d < bb->radius[p] + R && d > 0.0) depth += bb->radius[p] + R - d;
    }
    for (w = 0; w < MAX_WALLS; w++)
        if (wall_distance(inst, w, &ob[OX], &d, n) && d < R) depth += R - d;
    return c * depth > limit ? limit / depth : c;
}

/* Contact forces on object o (from the arm at bend angles q and rates rate, and the walls) with
 * Hunt-Crossley damping c: the force [N], torque [N m], dissipated power [W] and |F| sum. */
static void object_forces(const Instance *inst, const State *s, int o, const Backbone *bb,
                          const double v_arm[][2], double c, double F[2], double *torque,
                          double *dissipation, double *force_sum) {
    const double *ob = s->object[o], R = VI(inst, object_radius, o);
    int p, w;
    F[0] = F[1] = *torque = *dissipation = *force_sum = 0.0;
    for (p = 0; p < bb->n; p++) {
        const double r = bb->radius[p];
        double rel[2] = {bb->p[p][0] - ob[OX], bb->p[p][1] - ob[OY]}, d = hypot(rel[0], rel[1]);
        double n[2], vrel[2];
        Contact ct;
        if (d >= r + R || !(d > 0.0)) continue;
        n[0] = rel[0] / d, n[1] = rel[1] / d;
        vrel[0] = v_arm[p][0] - (ob[OVX] - ob[OW] * R * n[1]);
        vrel[1] = v_arm[p][1] - (ob[OVY] + ob[OW] * R * n[0]);
        contact_law(inst, r + R - d, n, vrel, V(inst, mu_arm), c, &ct);
        /* the reaction -F acts on the object's surface point R n */
        F[0] -= ct.F[0];
        F[1] -= ct.F[1];
        *torque -= R * (n[0] * ct.F[1] - n[1] * ct.F[0]);
        *dissipation += ct.dissipation;
        *force_sum += hypot(ct.F[0], ct.F[1]);
    }
    for (w = 0; w < MAX_WALLS; w++) {
        double d, n[2], arm[2], v[2];
        Contact ct;
        if (!wall_distance(inst, w, &ob[OX], &d, n) || d >= R) continue;
        arm[0] = -R * n[0], arm[1] = -R * n[1]; /* contact point relative to the centre */
        v[0] = ob[OVX] - ob[OW] * arm[1];
        v[1] = ob[OVY] + ob[OW] * arm[0];
        contact_law(inst, R - d, n, v, VI(inst, object_mu, o), c, &ct);
        F[0] += ct.F[0];
        F[1] += ct.F[1];
        *torque += arm[0] * ct.F[1] - arm[1] * ct.F[0];
        *dissipation += ct.dissipation;
        *force_sum += hypot(ct.F[0], ct.F[1]);
    }
}

/* Elastic energy of the objects' penetrations into the walls [J]. */
static double object_wall_elastic(const Instance *inst, const State *s) {
    double E = 0.0;
    int o, w;
    for (o = 0; o < (int)V(inst, n_objects); o++) {
        const double R = VI(inst, object_radius, o);
        for (w = 0; w < MAX_WALLS; w++) {
            double d, n[2];
            if (wall_distance(inst, w, &s->object[o][OX], &d, n) && d < R)
                E += 0.5 * V(inst, k_contact) * (R - d) * (R - d);
        }
    }
    return E;
}

static double kinetic_energy(const Instance *inst, const State *s) {
    double E = 0.0;
    int o;
    for (o = 0; o < (int)V(inst, n_objects); o++) {
        const double m = VI(inst, object_mass, o), R = VI(inst, object_radius, o);
        const double *ob = s->object[o];
        E += 0.5 * m * (ob[OVX] * ob[OVX] + ob[OVY] * ob[OVY]) +
             0.25 * m * R * R * ob[OW] * ob[OW];
    }
    return E;
}

/* Exact Coulomb table friction over dt: reduces a speed by at most the friction's impulse,
 * never reversing it. */
static double coulomb_stop(double speed, double decrement) {
    return speed > decrement ? speed - decrement : 0.0;
}

/* Whether the push F on object o tips it (an upright cylinder of radius R and height H). A
 * monitor, not fed back into the planar motion: the tilt phi about the base's edge on the far
 * side of the push obeys I_e phi'' = |F| h - m a_F H / 2 - m g (R cos phi - (H / 2) sin phi)
 * (moments about the edge, which moves with the object's acceleration a; a_F its component along
 * F; h = min(contact_height, H) the height of the push; I_e = m (15 R^2 + 4 H^2) / 12 about the
 * edge), phi >= 0 on the table (landing is inelastic). Past atan(2 R / H) the centre of mass is
 * beyond the edge: the object has fallen (latched). A light object pushed low slides rather
 * than tips: the inertial term carries most of the push. */
static void tip_over(const Instance *inst, State *s, int o, const double F[2], double ax,
                     double ay, double dt) {
    const double m = VI(inst, object_mass, o), R = VI(inst, object_radius, o);
    const double H = VI(inst, object_height, o), g = V(inst, gravity);
    const double h = V(inst, contact_height) < H ? V(inst, contact_height) : H;
    const double push = hypot(F[0], F[1]), Ie = m * (15.0 * R * R + 4.0 * H * H) / 12.0;
    double *tilt = s->tilt[o], along, moment;
    if (s->toppled[o]) return;
    along = push > 0.0 ? (ax * F[0] + ay * F[1]) / push : 0.0;
    moment = push * h - m * along * 0.5 * H - m * g * (R * cos(tilt[0]) - 0.5 * H * sin(tilt[0]));
    tilt[1] += dt * moment / Ie;
    tilt[0] += dt * tilt[1];
    if (tilt[0] <= 0.0) tilt[0] = tilt[1] = 0.0;
    if (tilt[0] >= atan2(2.0 * R, H)) s->toppled[o] = 1;
}

/* One semi-implicit Euler substep of the objects with the arm at theta + theta_dot t. */
void model_after_substep(Instance *inst, double dt) {
    State *s = (State *)inst->state;
    const int ns = n_dof(inst), no = (int)V(inst, n_objects);
    double q[MAX_DOF], v_arm[MAX_POINTS][2];
    Backbone bb;
    int o, p, i;
    if (no == 0) {
        s->t_step += dt;
        return;
    }
    for (i = 0; i < MAX_DOF; i++)
        q[i] = i < ns ? s->theta[i] + s->theta_dot[i] * s->t_step : 0.0;
    backbone(inst, q, &bb);
    for (p = 0; p < bb.n; p++) {
        v_arm[p][0] = v_arm[p][1] = 0.0;
        for (i = 0; i < ns; i++) {
            v_arm[p][0] += bb.J[p][i][0] * s->theta_dot[i];
            v_arm[p][1] += bb.J[p][i][1] * s->theta_dot[i];
        }
    }
    {
        double F[MAX_OBJECTS][2], T[MAX_OBJECTS];
        for (o = 0; o < no; o++) {
            double diss, fsum;
            const double c = object_damping(inst, s, o, &bb, dt);
            object_forces(inst, s, o, &bb, (const double(*)[2])v_arm, c, F[o], &T[o], &diss,
                          &fsum);
            s->E_diss += diss * dt;
            s->impulse += fsum * dt;
        }
        for (o = 0; o < no; o++) {
            double *ob = s->object[o];
            const double m = VI(inst, object_mass, o), R = VI(inst, object_radius, o);
            const double I = 0.5 * m * R * R, mug = V(inst, mu_table_object) * V(inst, gravity);
            double before, after, speed, x0 = ob[OX], y0 = ob[OY], yaw0 = ob[OYAW];
            const double vx0 = ob[OVX], vy0 = ob[OVY];
            ob[OVX] += dt * F[o][0] / m;
            ob[OVY] += dt * F[o][1] / m;
            ob[OW] += dt * T[o] / I;
            before = 0.5 * m * (ob[OVX] * ob[OVX] + ob[OVY] * ob[OVY]) + 0.5 * I * ob[OW] * ob[OW];
            speed = hypot(ob[OVX], ob[OVY]);
            if (speed > 0.0) {
                const double scale = coulomb_stop(speed, mug * dt) / speed;
                ob[OVX] *= scale;
                ob[OVY] *= scale;
            }
            /* friction torque of a uniformly pressed disk: (2/3) mu m g R */
            {
                const double dw = (2.0 / 3.0) * mug * m * R / I * dt;
                ob[OW] = ob[OW] > 0.0 ? coulomb_stop(ob[OW], dw) : -coulomb_stop(-ob[OW], dw);
            }
            after = 0.5 * m * (ob[OVX] * ob[OVX] + ob[OVY] * ob[OVY]) + 0.5 * I * ob[OW] * ob[OW];
            s->E_diss += before - after;
            tip_over(inst, s, o, F[o], (ob[OVX] - vx0) / dt, (ob[OVY] - vy0) / dt, dt);
            ob[OX] += dt * ob[OVX];
            ob[OY] += dt * ob[OVY];
            ob[OYAW] += dt * ob[OW];
            /* work of the contact forces over the displacement the integrator made */
            s->W_objects +=
                F[o][0] * (ob[OX] - x0) + F[o][1] * (ob[OY] - y0) + T[o] * (ob[OYAW] - yaw0);
        }
    }
    s->t_step += dt;
}

/* ---------------------------------------------------------------- FMI model contract */

/* Inputs of this step: bend angles and rates; the work of the torque that acted on the arm
 * since the previous step. */
fmi2Status model_step_start(Instance *inst) {
    State *s = (State *)inst->state;
    const int ns = n_segments(inst), nd = n_dof(inst);
    int i;
    for (i = 0; i < nd; i++) {
        const double theta =
            i < ns ? VI(inst, kappa, i) * VI(inst, length, i) : V(inst, gripper_theta);
        if (s->have_prev) s->W_arm += s->tau_now[i] * (theta - s->theta_prev[i]);
        s->theta_prev[i] = theta;
        s->theta[i] = theta;
        s->theta_dot[i] = i < ns ? VI(inst, theta_dot, i) : V(inst, gripper_theta_dot);
    }
    s->have_prev = 1;
    s->t_step = 0.0;
    return fmi2OK;
}

double model_time_to_event(const Instance *inst) {
    (void)inst;
    return INFINITY;
}

void model_discrete_update(Instance *inst) { (void)inst; }

int model_derivatives(const Instance *inst, const double y[], double dy[]) {
    (void)inst;
    (void)y;
    (void)dy;
    return 1; /* no continuous states: the objects are integrated in model_after_substep */
}

/* Passivity observer and controller (Hannaford and Ryu 2002): the energy the environment has
 * absorbed from the arm, -W_arm, less what it holds (elastic energy at the angles received, the
 * objects' kinetic energy), is what it has dissipated and cannot be negative for a passive
 * environment. If it is (the coupling's prediction missed the arm's real response), the coming
 * torque gets the damping beta that takes the deficit back over the next H at the rates
 * received: beta = deficit / (H sum theta_dot^2), at most PASSIVITY_MAX_GAIN / arm_mobility
 * [N m s/rad]; it is part of the implicit solve, so it cannot destabilise it. */
static double passivity_damping(const Instance *inst, const State *s, double H,
                                const ArmForces *now) {
    const int ns = n_dof(inst);
    const double m = V(inst, arm_mobility);
    double held, deficit, rates = 0.0, beta, limit;
    int i;
    if (!(H > 0.0) || m == 0.0) return 0.0;
    held = now->elastic + object_wall_elastic(inst, s) + kinetic_energy(inst, s);
    deficit = s->W_arm + held;
    if (!(deficit > 0.0)) return 0.0;
    for (i = 0; i < ns; i++) rates += s->theta_dot[i] * s->theta_dot[i];
    limit = PASSIVITY_MAX_GAIN / m;
    beta = rates > 0.0 ? deficit / (H * rates) : limit;
    return beta < limit ? beta : limit;
}

/* Solves the arm's torque for the coming step and sets every output. Called by the glue once at
 * the end of every step (s->t_step is then the step's length) and at initialisation (length 0). */
fmi2Status model_outputs(Instance *inst) {
    State *s = (State *)inst->state;
    const int ns = n_dof(inst);
    const double h = s->t_step, H = (1.0 + V(inst, coupling_delay)) * h;
    double tau[MAX_DOF];
    ArmForces out, now;
    int i, o;
    /* the state of the contact at the angles received; the torque solved for the coming step */
    arm_forces(inst, s, s->theta, s->theta_dot, 0.0, &now);
    s->beta = passivity_damping(inst, s, H, &now);
    V(inst, coupling_residual) = solve_arm_torque(inst, s, H, tau, &out);
    for (i = 0; i < MAX_DOF; i++) {
        if (!isfinite(tau[i])) {
            log_message(inst, fmi2Error, "the contact torque on segment %d is not finite", i + 1);
            return fmi2Error;
        }
    }
    /* the torque this step's output replaces acts on the arm from now on (Gauss-Seidel) or
     * after the next step (Jacobi) */
    for (i = 0; i < MAX_DOF; i++) {
        if (V(inst, coupling_delay) == 0.0) {
            s->tau_now[i] = tau[i];
        } else {
            s->tau_now[i] = s->tau_next[i];
            s->tau_next[i] = tau[i];
        }
    }
    for (i = 0; i < MAX_SEGMENTS; i++) {
        const int used = i < n_segments(inst);
        VI(inst, tau_ext, i) = used ? tau[i] : 0.0;
        VI(inst, penetration, i) = used ? now.penetration[i] : 0.0;
        VI(inst, contact_force, i) = used ? hypot(out.force[i][0], out.force[i][1]) : 0.0;
    }
    {
        const int g = n_segments(inst), used = ns > g; /* the fingers' degree of freedom */
        V(inst, gripper_tau_ext) = used ? tau[g] : 0.0;
        V(inst, gripper_penetration) = used ? now.penetration[g] : 0.0;
        V(inst, finger_force_left) = hypot(out.finger_force[0][0], out.finger_force[0][1]);
        V(inst, finger_force_right) = hypot(out.finger_force[1][0], out.finger_force[1][1]);
        V(inst, gripper_contact_force) = V(inst, finger_force_left) + V(inst, finger_force_right);
    }
    /* the arm's dissipation and impulse over the step in which this torque acts */
    s->E_diss += out.dissipation * h;
    s->impulse += out.force_sum * h;
    for (o = 0; o < MAX_OBJECTS; o++) {
        const double *ob = s->object[o];
        VI(inst, object_x, o) = ob[OX];
        VI(inst, object_y, o) = ob[OY];
        VI(inst, object_yaw, o) = ob[OYAW];
        VI(inst, object_vx, o) = ob[OVX];
        VI(inst, object_vy, o) = ob[OVY];
        VI(inst, object_omega, o) = ob[OW];
        VI(inst, object_upright, o) = s->toppled[o] ? 0.0 : 1.0;
        VI(inst, object_tilt, o) = s->tilt[o][0];
    }
    V(inst, contact_impulse) = s->impulse;
    V(inst, passivity_damping) = s->beta;
    V(inst, E_contact) = now.elastic + object_wall_elastic(inst, s);
    V(inst, E_kinetic) = kinetic_energy(inst, s);
    V(inst, E_dissipated) = s->E_diss;
    V(inst, W_arm) = s->W_arm;
    V(inst, W_objects) = s->W_objects;
    V(inst, W_contact) = s->W_arm + s->W_objects;
    return fmi2OK;
}

fmi2Status model_initialize(Instance *inst, OdeSystem *ode) {
    State *s = (State *)inst->state;
    const int no = (int)V(inst, n_objects);
    double limit = INFINITY;
    int o, i;
    memset(s, 0, sizeof *s);
    for (i = 0; i < (int)V(inst, n_walls); i++) {
        if (wall_vertices(inst, i) == 1) {
            log_message(inst, fmi2Error,
                        "invalid parameter wall%d_n = 1: a wall needs 0 or at least 2 vertices",
                        i + 1);
            return fmi2Error;
        }
    }
    for (o = 0; o < no; o++) {
        const double m = VI(inst, object_mass, o);
        s->object[o][OX] = VI(inst, object_x0, o);
        s->object[o][OY] = VI(inst, object_y0, o);
        s->object[o][OYAW] = VI(inst, object_yaw0, o);
        /* semi-implicit Euler on a penalty spring is stable below 2 / omega; damping and the
         * disk's rotation (I / R^2 = m / 2) halve the margin */
        if (V(inst, k_contact) > 0.0) {
            /* half the undamped limit: margin for the Hunt-Crossley damping */
            const double bound = 1.0 / sqrt(2.0 * V(inst, k_contact) / m);
            if (bound < limit) limit = bound;
        }
    }
    if (V(inst, substep) > limit) {
        log_message(inst, fmi2Error,
                    "invalid parameter substep = %g: beyond the stability limit %g s of the "
                    "objects' contact (k_contact, d_contact, object_mass)",
                    V(inst, substep), limit);
        return fmi2Error;
    }
    model_step_start(inst);
    s->have_prev = 1;
    ode->n = 0;
    ode->y = NULL;
    ode->max_substep = V(inst, substep);
    ode->stability_limit = limit;
    return model_outputs(inst);
}
