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
} Instance;

/* Value of variable `name` of instance `inst` (lvalue). */
#define V(inst, var) ((inst)->v[VR_##var])

/* Logs a message through the environment's logger; errors are always logged. */
void log_message(Instance *inst, fmi2Status status, const char *fmt, ...);

/* --- implemented by each model --- */
size_t model_state_size(void);
/* Checks parameters beyond their declared ranges, sets the initial state and the outputs.
 * Returns fmi2Error (after log_message) on an inconsistent parameter set. */
fmi2Status model_initialize(Instance *inst);
/* Advances the state by h seconds with the current inputs and updates the outputs. */
fmi2Status model_do_step(Instance *inst, double h);

#endif
