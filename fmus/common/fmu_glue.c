/* FMI 2.0 co-simulation glue, written once and compiled into every softhil FMU together with one
 * model's physics (see glue.h). It implements the FMI state machine, value-reference checks, type
 * checks, non-finite and range checks, FMU state save/restore and serialisation. Invariant: every
 * error returns fmi2Error after logging one message naming the instance, function and variable. */
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <string.h>

#include "glue.h"

static const char *const PHASE_NAMES[] = {"instantiated", "initialisation mode", "step mode",
                                          "terminated", "error"};

void log_message(Instance *inst, fmi2Status status, const char *fmt, ...) {
    char buffer[1024];
    va_list args;
    if (!inst || !inst->cb.logger) return;
    if (status == fmi2OK && !inst->logging_on) return;
    va_start(args, fmt);
    vsnprintf(buffer, sizeof buffer, fmt, args);
    va_end(args);
    inst->cb.logger(inst->cb.componentEnvironment, inst->name, status,
                    status == fmi2Error ? "logStatusError" : "logStatusWarning", "%s", buffer);
}

/* Returns 1 if `inst` may make `function` now, else logs and returns 0. `allowed` is a bit mask
 * of Phase values. */
static int phase_allows(Instance *inst, const char *function, unsigned allowed) {
    if (!inst) return 0;
    if (allowed & (1u << inst->phase)) return 1;
    log_message(inst, fmi2Error, "%s: not allowed in %s", function, PHASE_NAMES[inst->phase]);
    if (inst->phase != PHASE_TERMINATED) inst->phase = PHASE_ERROR;
    return 0;
}

#define ANY_LIVE ((1u << PHASE_INSTANTIATED) | (1u << PHASE_INIT) | (1u << PHASE_STEP) | \
                  (1u << PHASE_TERMINATED))

static int check_vr(Instance *inst, const char *function, fmi2ValueReference vr,
                    VariableType type) {
    static const char *const TYPE_NAMES[] = {"Real", "Integer", "Boolean"};
    if (vr >= N_VARIABLES) {
        log_message(inst, fmi2Error, "%s: unknown value reference %u", function, vr);
        return 0;
    }
    if (VARIABLES[vr].type != type) {
        log_message(inst, fmi2Error, "%s: variable %s is of type %s", function,
                    VARIABLES[vr].name, TYPE_NAMES[VARIABLES[vr].type]);
        return 0;
    }
    return 1;
}

/* Whether a variable of this causality may be set in the instance's current phase. */
static int settable(Instance *inst, const char *function, fmi2ValueReference vr) {
    const VariableInfo *info = &VARIABLES[vr];
    if (info->causality == CAUS_OUTPUT) {
        log_message(inst, fmi2Error, "%s: %s is an output and cannot be set", function, info->name);
        return 0;
    }
    if (info->causality == CAUS_PARAMETER && inst->phase == PHASE_STEP) {
        log_message(inst, fmi2Error, "%s: parameter %s is fixed after initialisation", function,
                    info->name);
        return 0;
    }
    return 1;
}

/* ---------------------------------------------------------------- common functions */

const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean loggingOn, size_t nCategories,
                               const fmi2String categories[]) {
    Instance *inst = (Instance *)c;
    (void)nCategories;
    (void)categories;
    if (!phase_allows(inst, "fmi2SetDebugLogging", ANY_LIVE)) return fmi2Error;
    inst->logging_on = loggingOn;
    return fmi2OK;
}

fmi2Component fmi2Instantiate(fmi2String instanceName, fmi2Type fmuType, fmi2String fmuGUID,
                              fmi2String fmuResourceLocation,
                              const fmi2CallbackFunctions *functions, fmi2Boolean visible,
                              fmi2Boolean loggingOn) {
    Instance *inst;
    size_t i;
    (void)fmuResourceLocation;
    (void)visible;
    if (!functions || !functions->allocateMemory || !functions->freeMemory) return NULL;
    if (!instanceName || !*instanceName) instanceName = MODEL_IDENTIFIER;
    inst = functions->allocateMemory(1, sizeof(Instance));
    if (!inst) return NULL;
    inst->cb = *functions;
    inst->logging_on = loggingOn;
    inst->name = functions->allocateMemory(strlen(instanceName) + 1, 1);
    inst->state = functions->allocateMemory(1, model_state_size());
    if (!inst->name || !inst->state) {
        if (inst->name) functions->freeMemory(inst->name);
        if (inst->state) functions->freeMemory(inst->state);
        functions->freeMemory(inst);
        return NULL;
    }
    strcpy(inst->name, instanceName);
    if (fmuType != fmi2CoSimulation) {
        log_message(inst, fmi2Error, "fmi2Instantiate: %s supports co-simulation only",
                    MODEL_IDENTIFIER);
        goto fail;
    }
    if (!fmuGUID || strcmp(fmuGUID, MODEL_GUID) != 0) {
        log_message(inst, fmi2Error, "fmi2Instantiate: GUID %s does not match %s (rebuild the FMU)",
                    fmuGUID ? fmuGUID : "(null)", MODEL_GUID);
        goto fail;
    }
    for (i = 0; i < N_VARIABLES; i++) inst->v[i] = VARIABLES[i].start;
    inst->phase = PHASE_INSTANTIATED;
    return inst;
fail:
    functions->freeMemory(inst->state);
    functions->freeMemory(inst->name);
    functions->freeMemory(inst);
    return NULL;
}

void fmi2FreeInstance(fmi2Component c) {
    Instance *inst = (Instance *)c;
    if (!inst) return;
    inst->cb.freeMemory(inst->state);
    inst->cb.freeMemory(inst->name);
    inst->cb.freeMemory(inst);
}

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean toleranceDefined, fmi2Real tolerance,
                               fmi2Real startTime, fmi2Boolean stopTimeDefined,
                               fmi2Real stopTime) {
    Instance *inst = (Instance *)c;
    (void)toleranceDefined;
    (void)tolerance;
    (void)stopTimeDefined;
    (void)stopTime;
    if (!phase_allows(inst, "fmi2SetupExperiment", 1u << PHASE_INSTANTIATED)) return fmi2Error;
    if (!isfinite(startTime)) {
        log_message(inst, fmi2Error, "fmi2SetupExperiment: non-finite start time");
        return fmi2Error;
    }
    inst->time = startTime;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c) {
    Instance *inst = (Instance *)c;
    if (!phase_allows(inst, "fmi2EnterInitializationMode", 1u << PHASE_INSTANTIATED))
        return fmi2Error;
    inst->phase = PHASE_INIT;
    inst->init_outputs_stale = 1;
    return fmi2OK;
}

/* Checks the parameters against their declared ranges and lets the model compute its initial
 * state and outputs from the parameters and inputs set so far. */
static fmi2Status initialize_from_values(Instance *inst) {
    fmi2Status status;
    size_t i;
    for (i = 0; i < N_VARIABLES; i++) {
        const VariableInfo *info = &VARIABLES[i];
        if (info->causality != CAUS_PARAMETER) continue;
        if ((info->has_min && inst->v[i] < info->min) || (info->has_max && inst->v[i] > info->max)) {
            log_message(inst, fmi2Error, "invalid parameter %s = %g: allowed range is [%g, %g]",
                        info->name, inst->v[i], info->has_min ? info->min : -INFINITY,
                        info->has_max ? info->max : INFINITY);
            return fmi2Error;
        }
    }
    inst->init_outputs_stale = 0;
    memset(&inst->ode, 0, sizeof inst->ode);
    status = model_initialize(inst, &inst->ode);
    if (status == fmi2OK && (inst->ode.n > MAX_STATES || (inst->ode.n > 0 && !inst->ode.y) ||
                             inst->ode.nb > MAX_BLOCK || inst->ode.nb > inst->ode.n ||
                             !(inst->ode.max_substep > 0.0))) {
        log_message(inst, fmi2Error, "model_initialize: inconsistent ODE system (%zu states)",
                    inst->ode.n);
        return fmi2Error;
    }
    return status;
}

fmi2Status fmi2ExitInitializationMode(fmi2Component c) {
    Instance *inst = (Instance *)c;
    if (!phase_allows(inst, "fmi2ExitInitializationMode", 1u << PHASE_INIT)) return fmi2Error;
    if (initialize_from_values(inst) != fmi2OK) {
        inst->phase = PHASE_ERROR;
        return fmi2Error;
    }
    inst->phase = PHASE_STEP;
    return fmi2OK;
}

/* In initialisation mode the outputs (the initial unknowns) must follow the values set so far:
 * a master propagating start values through connections reads them before exiting. */
static fmi2Status refresh_initial_outputs(Instance *inst) {
    if (inst->phase != PHASE_INIT || !inst->init_outputs_stale) return fmi2OK;
    return initialize_from_values(inst);
}

fmi2Status fmi2Terminate(fmi2Component c) {
    Instance *inst = (Instance *)c;
    if (!phase_allows(inst, "fmi2Terminate", (1u << PHASE_STEP) | (1u << PHASE_ERROR)))
        return fmi2Error;
    inst->phase = PHASE_TERMINATED;
    return fmi2OK;
}

fmi2Status fmi2Reset(fmi2Component c) {
    Instance *inst = (Instance *)c;
    size_t i;
    if (!inst) return fmi2Error;
    for (i = 0; i < N_VARIABLES; i++) inst->v[i] = VARIABLES[i].start;
    memset(inst->state, 0, model_state_size());
    inst->time = 0.0;
    inst->phase = PHASE_INSTANTIATED;
    return fmi2OK;
}

/* ---------------------------------------------------------------- getters and setters */

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                       fmi2Real value[]) {
    Instance *inst = (Instance *)c;
    size_t i;
    if (!phase_allows(inst, "fmi2GetReal", ANY_LIVE | (1u << PHASE_ERROR))) return fmi2Error;
    if (refresh_initial_outputs(inst) != fmi2OK) return fmi2Error;
    for (i = 0; i < nvr; i++) {
        if (!check_vr(inst, "fmi2GetReal", vr[i], VT_REAL)) return fmi2Error;
        value[i] = inst->v[vr[i]];
    }
    return fmi2OK;
}

fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                          fmi2Integer value[]) {
    Instance *inst = (Instance *)c;
    size_t i;
    if (!phase_allows(inst, "fmi2GetInteger", ANY_LIVE | (1u << PHASE_ERROR))) return fmi2Error;
    if (refresh_initial_outputs(inst) != fmi2OK) return fmi2Error;
    for (i = 0; i < nvr; i++) {
        if (!check_vr(inst, "fmi2GetInteger", vr[i], VT_INTEGER)) return fmi2Error;
        value[i] = (fmi2Integer)inst->v[vr[i]];
    }
    return fmi2OK;
}

fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                          fmi2Boolean value[]) {
    Instance *inst = (Instance *)c;
    size_t i;
    if (!phase_allows(inst, "fmi2GetBoolean", ANY_LIVE | (1u << PHASE_ERROR))) return fmi2Error;
    if (refresh_initial_outputs(inst) != fmi2OK) return fmi2Error;
    for (i = 0; i < nvr; i++) {
        if (!check_vr(inst, "fmi2GetBoolean", vr[i], VT_BOOLEAN)) return fmi2Error;
        value[i] = inst->v[vr[i]] != 0.0 ? fmi2True : fmi2False;
    }
    return fmi2OK;
}

fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                         fmi2String value[]) {
    Instance *inst = (Instance *)c;
    (void)vr;
    (void)value;
    if (nvr == 0) return fmi2OK;
    log_message(inst, fmi2Error, "fmi2GetString: %s has no String variables", MODEL_IDENTIFIER);
    return fmi2Error;
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                       const fmi2Real value[]) {
    Instance *inst = (Instance *)c;
    size_t i;
    if (!phase_allows(inst, "fmi2SetReal", ANY_LIVE & ~(1u << PHASE_TERMINATED))) return fmi2Error;
    for (i = 0; i < nvr; i++) {
        if (!check_vr(inst, "fmi2SetReal", vr[i], VT_REAL) || !settable(inst, "fmi2SetReal", vr[i]))
            return fmi2Error;
        if (!isfinite(value[i])) {
            log_message(inst, fmi2Error, "fmi2SetReal: non-finite value for %s",
                        VARIABLES[vr[i]].name);
            return fmi2Error;
        }
        inst->v[vr[i]] = value[i];
    }
    inst->init_outputs_stale = 1;
    return fmi2OK;
}

fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                          const fmi2Integer value[]) {
    Instance *inst = (Instance *)c;
    size_t i;
    if (!phase_allows(inst, "fmi2SetInteger", ANY_LIVE & ~(1u << PHASE_TERMINATED)))
        return fmi2Error;
    for (i = 0; i < nvr; i++) {
        if (!check_vr(inst, "fmi2SetInteger", vr[i], VT_INTEGER) ||
            !settable(inst, "fmi2SetInteger", vr[i]))
            return fmi2Error;
        inst->v[vr[i]] = (double)value[i];
    }
    inst->init_outputs_stale = 1;
    return fmi2OK;
}

fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                          const fmi2Boolean value[]) {
    Instance *inst = (Instance *)c;
    size_t i;
    if (!phase_allows(inst, "fmi2SetBoolean", ANY_LIVE & ~(1u << PHASE_TERMINATED)))
        return fmi2Error;
    for (i = 0; i < nvr; i++) {
        if (!check_vr(inst, "fmi2SetBoolean", vr[i], VT_BOOLEAN) ||
            !settable(inst, "fmi2SetBoolean", vr[i]))
            return fmi2Error;
        inst->v[vr[i]] = value[i] ? 1.0 : 0.0;
    }
    inst->init_outputs_stale = 1;
    return fmi2OK;
}

fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                         const fmi2String value[]) {
    Instance *inst = (Instance *)c;
    (void)vr;
    (void)value;
    if (nvr == 0) return fmi2OK;
    log_message(inst, fmi2Error, "fmi2SetString: %s has no String variables", MODEL_IDENTIFIER);
    return fmi2Error;
}

/* ---------------------------------------------------------------- FMU state */

typedef struct {
    Phase phase;
    double time;
    double v[N_VARIABLES];
} Snapshot; /* followed by model_state_size() bytes of model state */

static size_t snapshot_size(void) { return sizeof(Snapshot) + model_state_size(); }

static void save_snapshot(const Instance *inst, unsigned char *buffer) {
    Snapshot *s = (Snapshot *)buffer;
    s->phase = inst->phase;
    s->time = inst->time;
    memcpy(s->v, inst->v, sizeof s->v);
    memcpy(buffer + sizeof(Snapshot), inst->state, model_state_size());
}

static void load_snapshot(Instance *inst, const unsigned char *buffer) {
    const Snapshot *s = (const Snapshot *)buffer;
    inst->phase = s->phase;
    inst->time = s->time;
    memcpy(inst->v, s->v, sizeof s->v);
    memcpy(inst->state, buffer + sizeof(Snapshot), model_state_size());
}

fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *FMUstate) {
    Instance *inst = (Instance *)c;
    if (!phase_allows(inst, "fmi2GetFMUstate", ANY_LIVE)) return fmi2Error;
    if (!*FMUstate) *FMUstate = inst->cb.allocateMemory(1, snapshot_size());
    if (!*FMUstate) {
        log_message(inst, fmi2Error, "fmi2GetFMUstate: out of memory");
        return fmi2Error;
    }
    save_snapshot(inst, (unsigned char *)*FMUstate);
    return fmi2OK;
}

fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate FMUstate) {
    Instance *inst = (Instance *)c;
    if (!phase_allows(inst, "fmi2SetFMUstate", ANY_LIVE | (1u << PHASE_ERROR))) return fmi2Error;
    if (!FMUstate) {
        log_message(inst, fmi2Error, "fmi2SetFMUstate: null state");
        return fmi2Error;
    }
    load_snapshot(inst, (const unsigned char *)FMUstate);
    return fmi2OK;
}

fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *FMUstate) {
    Instance *inst = (Instance *)c;
    if (!inst || !FMUstate) return fmi2Error;
    if (*FMUstate) inst->cb.freeMemory(*FMUstate);
    *FMUstate = NULL;
    return fmi2OK;
}

fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate FMUstate, size_t *size) {
    (void)c;
    (void)FMUstate;
    *size = snapshot_size();
    return fmi2OK;
}

fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate FMUstate, fmi2Byte serializedState[],
                                 size_t size) {
    Instance *inst = (Instance *)c;
    if (!inst) return fmi2Error;
    if (size < snapshot_size()) {
        log_message(inst, fmi2Error, "fmi2SerializeFMUstate: buffer of %zu bytes, need %zu", size,
                    snapshot_size());
        return fmi2Error;
    }
    memcpy(serializedState, FMUstate, snapshot_size());
    return fmi2OK;
}

fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte serializedState[], size_t size,
                                   fmi2FMUstate *FMUstate) {
    Instance *inst = (Instance *)c;
    if (!inst) return fmi2Error;
    if (size != snapshot_size()) {
        log_message(inst, fmi2Error, "fmi2DeSerializeFMUstate: %zu bytes, expected %zu", size,
                    snapshot_size());
        return fmi2Error;
    }
    if (!*FMUstate) *FMUstate = inst->cb.allocateMemory(1, snapshot_size());
    if (!*FMUstate) return fmi2Error;
    memcpy(*FMUstate, serializedState, size);
    return fmi2OK;
}

fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference vUnknown_ref[],
                                        size_t nUnknown, const fmi2ValueReference vKnown_ref[],
                                        size_t nKnown, const fmi2Real dvKnown[],
                                        fmi2Real dvUnknown[]) {
    (void)vUnknown_ref;
    (void)nUnknown;
    (void)vKnown_ref;
    (void)nKnown;
    (void)dvKnown;
    (void)dvUnknown;
    log_message((Instance *)c, fmi2Error, "fmi2GetDirectionalDerivative: not provided");
    return fmi2Error;
}


/* ---------------------------------------------------------------- fixed-step solver */

/* phi_1..phi_3 of z (phi_k(z) = sum_j z^j / (j + k)!), by series near 0 where the closed forms
 * cancel, else closed form. */
static void phi_functions(double z, double phi[3]) {
    if (z == 0.0) {
        phi[0] = 1.0;
        phi[1] = 0.5;
        phi[2] = 1.0 / 6.0;
    } else if (fabs(z) < 0.5) {
        int k;
        for (k = 1; k <= 3; k++) {
            double term = 1.0, sum = 0.0, denominator = 1.0;
            int j;
            for (j = 1; j <= k; j++) denominator *= j;
            term = 1.0 / denominator;
            for (j = 0; j < 25; j++) {
                sum += term;
                term *= z / (j + k + 1);
            }
            phi[k - 1] = sum;
        }
    } else {
        const double e = exp(z);
        phi[0] = (e - 1.0) / z;
        phi[1] = (e - 1.0 - z) / (z * z);
        phi[2] = (e - 1.0 - z - 0.5 * z * z) / (z * z * z);
    }
}

/* N(y) = f(y) - L y, the part the exponential RK4 treats explicitly: L is the block A on the
 * first nb states and the diagonal lambda on the rest. */
static int nonlinear_part(const Instance *inst, const double y[], double out[]) {
    const OdeSystem *ode = &inst->ode;
    size_t j, k;
    if (!model_derivatives(inst, y, out)) return 0;
    for (j = 0; j < ode->nb; j++) {
        double linear = 0.0;
        for (k = 0; k < ode->nb; k++) linear += ode->A[j][k] * y[k];
        out[j] -= linear;
    }
    for (j = ode->nb; j < ode->n; j++) out[j] -= ode->lambda[j] * y[j];
    return 1;
}

#define MAX_AUGMENTED (4 * MAX_BLOCK)

/* C = A B for m x m matrices (m <= MAX_AUGMENTED); C may not alias A or B. */
static void matrix_product(size_t m, double A[][MAX_AUGMENTED], double B[][MAX_AUGMENTED],
                           double C[][MAX_AUGMENTED]) {
    /* The terms of a zero A[i][k] are left out: with B finite each is +-0, and a sum that
     * starts at +0.0 is never -0.0, so adding +-0 leaves it unchanged. The other terms are
     * added in the same order as the full product's, so C is the same bit for bit; the
     * augmented matrices are mostly zeros (W: one block and shifted identities). */
    size_t i, j, t, n, nonzero[MAX_AUGMENTED];
    for (i = 0; i < m; i++) {
        n = 0;
        for (t = 0; t < m; t++)
            if (A[i][t] != 0.0) nonzero[n++] = t;
        for (j = 0; j < m; j++) {
            double sum = 0.0;
            for (t = 0; t < n; t++) sum += A[i][nonzero[t]] * B[nonzero[t]][j];
            C[i][j] = sum;
        }
    }
}

/* e^M and phi_1..phi_3 of an nb x nb matrix M, from the exponential of the augmented matrix
 * W = [[M, I, 0, 0], [0, 0, I, 0], [0, 0, 0, I], [0, 0, 0, 0]], whose first block row is
 * [e^M, phi_1(M), phi_2(M), phi_3(M)] (Al-Mohy and Higham 2011, SIAM J. Sci. Comput. 33, 488,
 * theorem 2.1). exp(W) by scaling and squaring with a degree-18 Taylor polynomial once
 * ||W / 2^s||_1 <= 1/2 (truncation below 1e-21). out[k] receives phi_k, out[0] = e^M. */
static void block_phi_functions(size_t nb, double M[MAX_BLOCK][MAX_BLOCK],
                                double out[4][MAX_BLOCK][MAX_BLOCK]) {
    double W[MAX_AUGMENTED][MAX_AUGMENTED], T[MAX_AUGMENTED][MAX_AUGMENTED];
    double P[MAX_AUGMENTED][MAX_AUGMENTED];
    const size_t m = 4 * nb;
    double norm = 0.0, scale = 1.0;
    size_t i, j, b;
    int squarings = 0, degree;
    memset(W, 0, sizeof W);
    for (i = 0; i < nb; i++) {
        for (j = 0; j < nb; j++) W[i][j] = M[i][j];
        for (b = 1; b < 4; b++) W[(b - 1) * nb + i][b * nb + i] = 1.0;
    }
    for (j = 0; j < m; j++) {
        double column = 0.0;
        for (i = 0; i < m; i++) column += fabs(W[i][j]);
        if (column > norm) norm = column;
    }
    while (norm * scale > 0.5) {
        scale *= 0.5;
        squarings++;
    }
    for (i = 0; i < m; i++)
        for (j = 0; j < m; j++) W[i][j] *= scale;
    /* Horner: T = I + W/1 (I + W/2 (I + ... (I + W/18))) */
    for (i = 0; i < m; i++)
        for (j = 0; j < m; j++) T[i][j] = i == j ? 1.0 : 0.0;
    for (degree = 18; degree >= 1; degree--) {
        matrix_product(m, W, T, P);
        for (i = 0; i < m; i++)
            for (j = 0; j < m; j++) T[i][j] = (i == j ? 1.0 : 0.0) + P[i][j] / degree;
    }
    for (; squarings > 0; squarings--) {
        matrix_product(m, T, T, P);
        memcpy(T, P, sizeof T);
    }
    for (b = 0; b < 4; b++)
        for (i = 0; i < nb; i++)
            for (j = 0; j < nb; j++) out[b][i][j] = T[i][b * nb + j];
}

/* The coefficients of one ETDRK4 substep of length h (Cox and Matthews 2002, J. Comput. Phys.
 * 176, 430): scalars for the diagonal states, matrices for the block. A set computed for the same
 * h, rates and block is reused; otherwise the set is computed into the next slot. */
static const Coefficients *exponential_coefficients(OdeSystem *ode, double h) {
    Coefficients *set;
    size_t j, k, slot;
    for (slot = 0; slot < COEF_SLOTS; slot++) {
        int same;
        set = &ode->coef[slot];
        same = set->h == h;
        for (j = 0; same && j < ode->n; j++) same = set->lambda[j] == ode->lambda[j];
        if (same && ode->nb > 0) same = memcmp(set->A, ode->A, sizeof ode->A) == 0;
        if (same) return set;
    }
    set = &ode->coef[ode->coef_next];
    ode->coef_next = (ode->coef_next + 1) % COEF_SLOTS;
    for (j = 0; j < ode->n; j++) {
        const double z = ode->lambda[j] * h;
        double phi[3], phi_half[3];
        phi_functions(z, phi);
        phi_functions(0.5 * z, phi_half);
        set->E[j] = z == 0.0 ? 1.0 : exp(z);
        set->E2[j] = z == 0.0 ? 1.0 : exp(0.5 * z);
        set->p_half[j] = 0.5 * h * phi_half[0];
        set->f1[j] = h * (phi[0] - 3.0 * phi[1] + 4.0 * phi[2]);
        set->f2[j] = h * (phi[1] - 2.0 * phi[2]);
        set->f3[j] = h * (-phi[1] + 4.0 * phi[2]);
        set->lambda[j] = ode->lambda[j];
    }
    if (ode->nb > 0) {
        double M[MAX_BLOCK][MAX_BLOCK], M_half[MAX_BLOCK][MAX_BLOCK];
        double phi[4][MAX_BLOCK][MAX_BLOCK], phi_half[4][MAX_BLOCK][MAX_BLOCK];
        memset(M, 0, sizeof M);
        memset(M_half, 0, sizeof M_half);
        for (j = 0; j < ode->nb; j++) {
            for (k = 0; k < ode->nb; k++) {
                M[j][k] = ode->A[j][k] * h;
                M_half[j][k] = 0.5 * M[j][k];
            }
        }
        block_phi_functions(ode->nb, M, phi);
        block_phi_functions(ode->nb, M_half, phi_half);
        for (j = 0; j < ode->nb; j++) {
            for (k = 0; k < ode->nb; k++) {
                set->bE[j][k] = phi[0][j][k];
                set->bE2[j][k] = phi_half[0][j][k];
                set->bp_half[j][k] = 0.5 * h * phi_half[1][j][k];
                set->bf1[j][k] = h * (phi[1][j][k] - 3.0 * phi[2][j][k] + 4.0 * phi[3][j][k]);
                set->bf2[j][k] = h * (phi[2][j][k] - 2.0 * phi[3][j][k]);
                set->bf3[j][k] = h * (-phi[2][j][k] + 4.0 * phi[3][j][k]);
            }
        }
        memcpy(set->A, ode->A, sizeof ode->A);
    }
    set->h = h;
    return set;
}

/* out = M v over the block (nb entries). */
static void block_apply(size_t nb, const double M[MAX_BLOCK][MAX_BLOCK], const double v[],
                        double out[]) {
    size_t j, k;
    for (j = 0; j < nb; j++) {
        double sum = 0.0;
        for (k = 0; k < nb; k++) sum += M[j][k] * v[k];
        out[j] = sum;
    }
}

/* One substep of ETDRK4 of length h; returns 0 if a stage left the model's domain or became
 * non-finite. The block states take the same stages with matrix coefficients. */
static int exponential_rk4(Instance *inst, double h) {
    OdeSystem *ode = &inst->ode;
    double *y = ode->y;
    double Nu[MAX_STATES], Na[MAX_STATES], Nb[MAX_STATES], Nc[MAX_STATES];
    double a[MAX_STATES], b[MAX_STATES], c[MAX_STATES];
    double t1[MAX_BLOCK], t2[MAX_BLOCK], t3[MAX_BLOCK], t4[MAX_BLOCK], w[MAX_BLOCK];
    const Coefficients *coef = exponential_coefficients(ode, h);
    const double *E = coef->E, *E2 = coef->E2, *p_half = coef->p_half;
    const double *f1 = coef->f1, *f2 = coef->f2, *f3 = coef->f3;
    const size_t nb = ode->nb;
    size_t j;
    if (!nonlinear_part(inst, y, Nu)) return 0;
    block_apply(nb, coef->bE2, y, t1);
    block_apply(nb, coef->bp_half, Nu, t2);
    for (j = 0; j < nb; j++) a[j] = t1[j] + t2[j];
    for (j = nb; j < ode->n; j++) a[j] = E2[j] * y[j] + p_half[j] * Nu[j];
    if (!nonlinear_part(inst, a, Na)) return 0;
    block_apply(nb, coef->bp_half, Na, t2);
    for (j = 0; j < nb; j++) b[j] = t1[j] + t2[j];
    for (j = nb; j < ode->n; j++) b[j] = E2[j] * y[j] + p_half[j] * Na[j];
    if (!nonlinear_part(inst, b, Nb)) return 0;
    for (j = 0; j < nb; j++) w[j] = 2.0 * Nb[j] - Nu[j];
    block_apply(nb, coef->bE2, a, t1);
    block_apply(nb, coef->bp_half, w, t2);
    for (j = 0; j < nb; j++) c[j] = t1[j] + t2[j];
    for (j = nb; j < ode->n; j++) c[j] = E2[j] * a[j] + p_half[j] * (2.0 * Nb[j] - Nu[j]);
    if (!nonlinear_part(inst, c, Nc)) return 0;
    block_apply(nb, coef->bE, y, t1);
    block_apply(nb, coef->bf1, Nu, t2);
    for (j = 0; j < nb; j++) w[j] = Na[j] + Nb[j];
    block_apply(nb, coef->bf2, w, t3);
    block_apply(nb, coef->bf3, Nc, t4);
    for (j = 0; j < nb; j++) {
        y[j] = t1[j] + t2[j] + 2.0 * t3[j] + t4[j];
        if (!isfinite(y[j])) return 0;
    }
    for (j = nb; j < ode->n; j++) {
        y[j] = E[j] * y[j] + f1[j] * Nu[j] + 2.0 * f2[j] * (Na[j] + Nb[j]) + f3[j] * Nc[j];
        if (!isfinite(y[j])) return 0;
    }
    return 1;
}

/* One substep of length h, in the equal parts the model asks for at its start (`parts`, rounded
 * up to a power of two, at most MAX_PARTS), each followed by the model's projection; returns 0
 * as exponential_rk4 does. */
static int refined_substep(Instance *inst, double h) {
    const int asked = inst->ode.n > 0 && inst->ode.parts ? inst->ode.parts(inst, h) : 1;
    int parts = 1, k;
    while (parts < asked && parts < MAX_PARTS) parts *= 2;
    for (k = 0; k < parts; k++) {
        if (inst->ode.n > 0 && !exponential_rk4(inst, h / parts)) return 0;
        model_after_substep(inst, h / parts);
    }
    return 1;
}

/* Advances the model by h: discrete updates at their times, equal substeps no longer than
 * max_substep between them (each split further where the model asks, refined_substep). A
 * substep that fails is reported as divergence, with the limit. */
static fmi2Status solve_step(Instance *inst, double h) {
    const double eps = 1e-12 * (h > inst->ode.max_substep ? h : inst->ode.max_substep);
    double remaining = h, t = inst->time;
    if (model_step_start(inst) != fmi2OK) return fmi2Error;
    while (remaining > eps) {
        double dt, n;
        if (model_time_to_event(inst) <= eps) model_discrete_update(inst);
        dt = model_time_to_event(inst);
        if (!(dt < remaining)) dt = remaining;
        n = ceil(dt / inst->ode.max_substep - 1e-9);
        if (n > 1.0) dt /= n;
        if (!refined_substep(inst, dt)) {
            log_message(inst, fmi2Error,
                        "the integrator diverged at t = %g (substep %g s, limit %g s): the state "
                        "became non-finite or left the model's domain",
                        t, dt, inst->ode.stability_limit);
            return fmi2Error;
        }
        remaining -= dt;
        t += dt;
    }
    return model_outputs(inst);
}

/* ---------------------------------------------------------------- co-simulation */

fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                       const fmi2Integer order[], const fmi2Real value[]) {
    (void)vr;
    (void)nvr;
    (void)order;
    (void)value;
    log_message((Instance *)c, fmi2Error, "fmi2SetRealInputDerivatives: not provided");
    return fmi2Error;
}

fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[],
                                        size_t nvr, const fmi2Integer order[], fmi2Real value[]) {
    (void)vr;
    (void)nvr;
    (void)order;
    (void)value;
    log_message((Instance *)c, fmi2Error, "fmi2GetRealOutputDerivatives: not provided");
    return fmi2Error;
}

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real currentCommunicationPoint,
                      fmi2Real communicationStepSize, fmi2Boolean noSetFMUStatePriorToCurrentPoint) {
    Instance *inst = (Instance *)c;
    (void)noSetFMUStatePriorToCurrentPoint;
    if (!phase_allows(inst, "fmi2DoStep", 1u << PHASE_STEP)) return fmi2Error;
    if (!(communicationStepSize > 0.0) || !isfinite(communicationStepSize)) {
        log_message(inst, fmi2Error, "fmi2DoStep: step size %g must be positive and finite",
                    communicationStepSize);
        return fmi2Error;
    }
    if (fabs(currentCommunicationPoint - inst->time) > 1e-9 * (1.0 + fabs(inst->time))) {
        log_message(inst, fmi2Error, "fmi2DoStep: communication point %.12g but the FMU is at %.12g",
                    currentCommunicationPoint, inst->time);
        return fmi2Error;
    }
    if (solve_step(inst, communicationStepSize) != fmi2OK) {
        inst->phase = PHASE_ERROR;
        return fmi2Error;
    }
    inst->time = currentCommunicationPoint + communicationStepSize;
    return fmi2OK;
}

fmi2Status fmi2CancelStep(fmi2Component c) {
    log_message((Instance *)c, fmi2Error, "fmi2CancelStep: steps are synchronous");
    return fmi2Error;
}

fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *value) {
    (void)c;
    (void)s;
    *value = fmi2OK;
    return fmi2Discard;
}

fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *value) {
    Instance *inst = (Instance *)c;
    if (inst && s == fmi2LastSuccessfulTime) {
        *value = inst->time;
        return fmi2OK;
    }
    return fmi2Discard;
}

fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *value) {
    (void)c;
    (void)s;
    (void)value;
    return fmi2Discard;
}

fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *value) {
    (void)c;
    (void)s;
    (void)value;
    return fmi2Discard;
}

fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *value) {
    (void)c;
    (void)s;
    (void)value;
    return fmi2Discard;
}
