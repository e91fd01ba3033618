/* The contract between the FMI 2.0 co-simulation glue (fmu_glue.c, written once) and a model's
 * physics (models/NAME/model.c). The glue owns the instance, the variable table generated from
 * model.toml (model_variables.h), the FMI state machine and all argument checks; a model owns only
 * its private state struct and three functions. Invariant: physics code never sees an FMI call
 * out of sequence, a non-finite input or a parameter outside its declared range. */
#ifndef SOFTHIL_GLUE_H
#define SOFTHIL_GLUE_H

#include <stddef.h>

#include "fmi2Functions.h"

typedef enum { VT_REAL, VT_INTEGER, VT_BOOLEAN } VariableType;
typedef enum { CAUS_PARAMETER, CAUS_INPUT, CAUS_OUTPUT } VariableCausality;

typedef struct {
    const char *name;
    VariableType type;
    VariableCausality causality;
    double start;
    int has_min, has_max;
    double min, max;
} VariableInfo;

#include "model_variables.h" /* generated: MODEL_IDENTIFIER, MODEL_GUID, VR_*, N_VARIABLES */

/* Continuous states of a model and how the fixed-step solver treats them (see below). */
#define MAX_STATES 40 /* the most: ArmBody, 16 coordinates, their rates and 3 energy integrals */
#define MAX_BLOCK 4

/* The exponential RK4's coefficients for one substep length h, the rates lambda and the block A
 * (diagonal states keep scalars, the block keeps the same coefficients as matrices, functions of
 * h A); h = 0 means none yet. */
typedef struct {
    double h;
    double lambda[MAX_STATES];
    double A[MAX_BLOCK][MAX_BLOCK];
    double E[MAX_STATES], E2[MAX_STATES], p_half[MAX_STATES];
    double f1[MAX_STATES], f2[MAX_STATES], f3[MAX_STATES];
    double bE[MAX_BLOCK][MAX_BLOCK], bE2[MAX_BLOCK][MAX_BLOCK], bp_half[MAX_BLOCK][MAX_BLOCK];
    double bf1[MAX_BLOCK][MAX_BLOCK], bf2[MAX_BLOCK][MAX_BLOCK], bf3[MAX_BLOCK][MAX_BLOCK];
} Coefficients;

/* coefficient sets kept: the substep and its refinements by 2, 4 and 8 (see `parts`) */
#define COEF_SLOTS 4
#define MAX_PARTS 8

struct Instance;

typedef struct {
    size_t n;                   /* number of continuous states, <= MAX_STATES */
    double *y;                  /* the states, inside the model's state struct */
    /* the stiff linear part integrated exactly: the first nb states (nb <= MAX_BLOCK) form a
     * coupled linear block with the dense matrix A [1/s]; every later state j may have its own
     * diagonal rate lambda[j] [1/s] (0 if none; lambda of block states is unused) */
    size_t nb;
    double A[MAX_BLOCK][MAX_BLOCK];
    double lambda[MAX_STATES];
    double max_substep;         /* largest substep [s], the model's `substep` parameter */
    double stability_limit;     /* the substep beyond which the model states the solver diverges */
    /* optional: into how many equal parts a substep of length h starting from the current state
     * must be split for accuracy (a stiffness of the explicit part that only some states have,
     * such as smoothed Coulomb friction near zero velocity); rounded up to a power of two, at
     * most MAX_PARTS. NULL: never split. */
    int (*parts)(const struct Instance *inst, double h);
    /* the coefficients for the last substep lengths: the substep is nearly always one of a few,
     * so they are computed once per length, not every substep (the same values bit for bit) */
    Coefficients coef[COEF_SLOTS];
    size_t coef_next;           /* the slot a new length takes (round robin) */
} OdeSystem;

typedef enum { PHASE_INSTANTIATED, PHASE_INIT, PHASE_STEP, PHASE_TERMINATED, PHASE_ERROR } Phase;

typedef struct Instance {
    char *name;
    fmi2CallbackFunctions cb;
    int logging_on;
    Phase phase;
    double time;
    int init_outputs_stale; /* an input or parameter changed in initialisation mode */
    double v[N_VARIABLES];  /* every variable, indexed by value reference */
    void *state;           /* the model's private state, model_state_size() bytes */
    OdeSystem ode;         /* the continuous states the solver integrates */
} Instance;

/* Value of variable `name` of instance `inst` (lvalue). */
#define V(inst, var) ((inst)->v[VR_##var])

/* Logs a message through the environment's logger; errors are always logged. */
void log_message(Instance *inst, fmi2Status status, const char *fmt, ...);

/* --- implemented by each model --- */
/* The fixed-step solver (fmu_glue.c) integrates the model's continuous states y[0..n-1], which
 * live in the model's state struct; a model supplies only its derivatives, its discrete updates
 * (sampled firmware, input events) and its checks. The solver is the exponential RK4 of Cox and
 * Matthews (2002): each state may declare a stiff linear rate lambda_j (dy_j/dt = lambda_j y_j +
 * N_j(y)), and the first nb states a coupled stiff linear block A (dy/dt = A y + N(y)), that are
 * integrated exactly over a substep; with nb = 0 and every lambda_j = 0 it is the classical RK4.
 * A coupled block matters when stiff states drive each other (a motor's current and speed): a
 * diagonal rate alone leaves the coupling explicit, and its error then limits the substep. */

size_t model_state_size(void);
/* Checks parameters beyond their declared ranges, sets the initial state, fills `ode` and sets the
 * outputs. Returns fmi2Error (after log_message) on an inconsistent parameter set, including a
 * substep beyond the model's stated stability limit. */
fmi2Status model_initialize(Instance *inst, OdeSystem *ode);
/* Discrete update at the start of a communication step (input events); fmi2Error after a message
 * if an input is unusable. */
fmi2Status model_step_start(Instance *inst);
/* Time until the model's next discrete update inside a step (sampled firmware) [s], INFINITY if
 * none; the solver ends a substep there and calls model_discrete_update. */
double model_time_to_event(const Instance *inst);
void model_discrete_update(Instance *inst);
/* dy/dt at y. Returns 0 if y lies outside the model's domain (the integrator diverged). */
int model_derivatives(const Instance *inst, const double y[], double dy[]);
/* Projection after a substep of length dt (end stops, mechanical limits), event clocks. */
void model_after_substep(Instance *inst, double dt);
/* Sets the outputs from the state; fmi2Error after a message if the state is unphysical. */
fmi2Status model_outputs(Instance *inst);

#endif
