/* The stepping kernel: Jacobi macro steps of FMU instances between two SYNCs, in C.
 *
 * hil/cosim/algorithm.py is the reference; this file does exactly what Algorithm._step_once does for FMU
 * participants, through the FMI 2.0 function pointers of the libraries fmpy loaded:
 *   for each tick k in [k_begin, k_end):
 *     every FMU due at k (k % decimation == 0) gets each input that has a source
 *       (an external value, or gain * values[source] + offset from the values at the start of the
 *       tick), set only when it differs from what was last set (as FmuParticipant.set_inputs),
 *       then fmi2DoStep(k * h, decimation * h);
 *     then every due FMU's outputs are read into values[] (fmi2GetReal, then the other types).
 * Time is (double)k * h and the step (double)d * h, as `k * self.step` in Python. The build
 * passes -ffp-contract=off so that gain * v + offset is rounded twice, as in Python.
 * No global state: everything is in the Plan the caller owns.
 *
 * A Worker steps the same way on a thread of its own (softhil_worker_*), so that the caller can
 * compute while the FMUs step: the caller starts a job and later waits for it; while a job runs,
 * the caller touches neither the plan, nor the values, nor the FMU instances. At each sample tick
 * the job copies values[] as it stands at the start of that tick (what a participant stepped in
 * Python at that tick reads), so the caller can step those participants afterwards. Both sides
 * poll for a while, yielding the core at each poll, before they sleep: waking a sleeping thread
 * costs hundreds of microseconds on a virtual machine, more than a job takes.
 */
#define _GNU_SOURCE /* pthread_setname_np */
#include <pthread.h>
#include <sched.h>
#include <stddef.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#define EXPORT __attribute__((visibility("default")))

typedef void *fmi2Component;
typedef unsigned int fmi2ValueReference;
typedef int fmi2Status; /* fmi2OK 0, fmi2Warning 1, fmi2Discard 2, fmi2Error 3, fmi2Fatal 4 */
typedef fmi2Status (*SetReal)(fmi2Component, const fmi2ValueReference[], size_t, const double[]);
typedef fmi2Status (*GetReal)(fmi2Component, const fmi2ValueReference[], size_t, double[]);
typedef fmi2Status (*SetInt)(fmi2Component, const fmi2ValueReference[], size_t, const int[]);
typedef fmi2Status (*GetInt)(fmi2Component, const fmi2ValueReference[], size_t, int[]);
typedef fmi2Status (*DoStep)(fmi2Component, double, double, int);

enum { TYPE_REAL = 0, TYPE_INTEGER = 1, TYPE_BOOLEAN = 2 };
enum { SOURCE_NONE = 0, SOURCE_EXTERNAL = 1, SOURCE_CONNECTION = 2 };
/* which call failed, reported in Failure.function (names are made in Python) */
enum {
    CALL_SET_REAL = 0,
    CALL_DO_STEP = 1,
    CALL_GET_REAL = 2,
    CALL_SET_INTEGER = 3,
    CALL_SET_BOOLEAN = 4,
    CALL_GET_INTEGER = 5,
    CALL_GET_BOOLEAN = 6
};

typedef struct {
    int n_fmus;
    /* per FMU f */
    void **component;
    void **set_real, **get_real, **set_integer, **get_integer, **set_boolean, **get_boolean;
    void **do_step;
    const int *decimation;
    const int *input_begin;  /* inputs of f are [input_begin[f], input_begin[f + 1]) */
    const int *output_begin; /* outputs of f are [output_begin[f], output_begin[f + 1]) */
    /* per input i */
    const unsigned int *input_vr;
    const int *input_type;
    int *input_source;        /* SOURCE_*; an external value may appear between runs */
    const int *input_slot;    /* values[] index of the connected output */
    const double *input_gain;
    const double *input_offset;
    double *input_external;
    double *input_last;       /* what was last set, valid where input_has_last */
    int *input_has_last;
    /* per output o */
    const unsigned int *output_vr;
    const int *output_type;
    const int *output_slot;
    /* scratch, at least max inputs (outputs) of one FMU */
    unsigned int *scratch_vr;
    double *scratch_real;
} Plan;

typedef struct {
    long long tick;
    int fmu;
    int function; /* CALL_* */
    int index;    /* the input or output of a by-name call, else -1 */
    int status;
} Failure;

static int failed(Failure *failure, long long k, int f, int function, int index, int status) {
    failure->tick = k;
    failure->fmu = f;
    failure->function = function;
    failure->index = index;
    failure->status = status;
    return 1;
}

static int set_inputs(const Plan *plan, int f, const double *values, long long k,
                      Failure *failure) {
    void *c = plan->component[f];
    size_t n_real = 0;
    for (int i = plan->input_begin[f]; i < plan->input_begin[f + 1]; ++i) {
        double value;
        if (plan->input_source[i] == SOURCE_CONNECTION)
            value = plan->input_gain[i] * values[plan->input_slot[i]] + plan->input_offset[i];
        else if (plan->input_source[i] == SOURCE_EXTERNAL)
            value = plan->input_external[i];
        else
            continue;
        if (plan->input_has_last[i] && plan->input_last[i] == value) continue;
        plan->input_has_last[i] = 1;
        plan->input_last[i] = value;
        const fmi2ValueReference vr = plan->input_vr[i];
        if (plan->input_type[i] == TYPE_REAL) {
            plan->scratch_vr[n_real] = vr;
            plan->scratch_real[n_real] = value;
            ++n_real;
        } else if (plan->input_type[i] == TYPE_INTEGER) {
            const int v = (int)value;
            const fmi2Status s = ((SetInt)plan->set_integer[f])(c, &vr, 1, &v);
            if (s > 1) return failed(failure, k, f, CALL_SET_INTEGER, i, s);
        } else {
            const int v = value != 0.0;
            const fmi2Status s = ((SetInt)plan->set_boolean[f])(c, &vr, 1, &v);
            if (s > 1) return failed(failure, k, f, CALL_SET_BOOLEAN, i, s);
        }
    }
    if (n_real > 0) {
        const fmi2Status s =
            ((SetReal)plan->set_real[f])(c, plan->scratch_vr, n_real, plan->scratch_real);
        if (s > 1) return failed(failure, k, f, CALL_SET_REAL, -1, s);
    }
    return 0;
}

static int get_outputs(const Plan *plan, int f, double *values, long long k, Failure *failure) {
    void *c = plan->component[f];
    size_t n_real = 0;
    for (int o = plan->output_begin[f]; o < plan->output_begin[f + 1]; ++o)
        if (plan->output_type[o] == TYPE_REAL) plan->scratch_vr[n_real++] = plan->output_vr[o];
    if (n_real > 0) {
        const fmi2Status s =
            ((GetReal)plan->get_real[f])(c, plan->scratch_vr, n_real, plan->scratch_real);
        if (s > 1) return failed(failure, k, f, CALL_GET_REAL, -1, s);
    }
    size_t r = 0;
    for (int o = plan->output_begin[f]; o < plan->output_begin[f + 1]; ++o) {
        if (plan->output_type[o] == TYPE_REAL) {
            values[plan->output_slot[o]] = plan->scratch_real[r++];
            continue;
        }
        const fmi2ValueReference vr = plan->output_vr[o];
        int v = 0;
        const int boolean = plan->output_type[o] == TYPE_BOOLEAN;
        const fmi2Status s = ((GetInt)(boolean ? plan->get_boolean[f] : plan->get_integer[f]))(
            c, &vr, 1, &v);
        if (s > 1)
            return failed(failure, k, f, boolean ? CALL_GET_BOOLEAN : CALL_GET_INTEGER, o, s);
        values[plan->output_slot[o]] = boolean ? (v != 0 ? 1.0 : 0.0) : (double)v;
    }
    return 0;
}

/* Ticks k_begin .. k_end - 1; at each of the n_samples ascending sample_ticks, values[] (n_values)
 * is copied into the next row of samples before that tick is stepped. */
static int advance(const Plan *plan, double *values, long long k_begin, long long k_end, double h,
                   const long long *sample_ticks, int n_samples, double *samples, int n_values,
                   long long *ticks_done, Failure *failure) {
    int sample = 0;
    for (long long k = k_begin; k < k_end; ++k) {
        *ticks_done = k;
        if (sample < n_samples && sample_ticks[sample] == k) {
            memcpy(samples + (size_t)sample * (size_t)n_values, values,
                   (size_t)n_values * sizeof(double));
            ++sample;
        }
        for (int f = 0; f < plan->n_fmus; ++f) {
            const int d = plan->decimation[f];
            if (k % d != 0) continue;
            if (set_inputs(plan, f, values, k, failure)) return 1;
            const fmi2Status s =
                ((DoStep)plan->do_step[f])(plan->component[f], (double)k * h, (double)d * h, 1);
            if (s > 1) return failed(failure, k, f, CALL_DO_STEP, -1, s);
        }
        for (int f = 0; f < plan->n_fmus; ++f) {
            if (k % plan->decimation[f] != 0) continue;
            if (get_outputs(plan, f, values, k, failure)) return 1;
        }
    }
    *ticks_done = k_end;
    return 0;
}

/* Step ticks k_begin .. k_end - 1. Returns 0, or 1 with *failure filled and *ticks_done the
 * failing tick (values[] then holds the outputs published at the start of that tick). */
EXPORT int softhil_advance(const Plan *plan, double *values, long long k_begin, long long k_end,
                           double h, long long *ticks_done, Failure *failure) {
    return advance(plan, values, k_begin, k_end, h, NULL, 0, NULL, 0, ticks_done, failure);
}

/* The worker: its states, each written by one side only (the caller: IDLE, PENDING, QUIT; the
 * thread: DONE). Each side waits for the other by polling for `spin` seconds (yielding the core),
 * then sleeping on the condition variable; a side that changes the state wakes the other only if
 * it sleeps. Waking a sleeping thread is a system call and, on a virtual machine, an interrupt
 * to another virtual CPU: 10-14 us measured here, which is what a period's hand-over cost when
 * the thread slept between jobs (it now polls between them, as the caller does for its end).
 * The state and the count of sleepers are sequentially consistent atomics, so a changer either
 * sees the sleeper or the sleeper sees the change before it sleeps. */
enum { IDLE = 0, PENDING = 1, DONE = 2, QUIT = 3 };

/* A job, in memory the caller owns (hil.cosim.kernel._Job mirrors it): written before each
 * softhil_worker_go, read by the thread once it sees PENDING. Passing it so, not as ten
 * arguments of a call, spares the caller ctypes' conversion of each (3 us a job, measured). */
typedef struct {
    const Plan *plan;
    double *values;
    long long k_begin, k_end;
    double h;
    const long long *sample_ticks;
    int n_samples;
    double *samples;
    int n_values;
} Job;

typedef struct {
    const Job *job;
    /* the outcome, valid once DONE */
    int result;
    long long ticks_done;
    Failure failure;
    int state;
    int sleepers; /* threads in pthread_cond_wait, or about to be */
    double spin;  /* [s] either side polls for the other before it sleeps */
    pthread_mutex_t mutex;
    pthread_cond_t changed;
    pthread_t thread;
} Worker;

static int state_of(Worker *w) { return __atomic_load_n(&w->state, __ATOMIC_SEQ_CST); }

static void publish(Worker *w, int state) {
    __atomic_store_n(&w->state, state, __ATOMIC_SEQ_CST);
    if (__atomic_load_n(&w->sleepers, __ATOMIC_SEQ_CST)) {
        pthread_mutex_lock(&w->mutex);
        pthread_cond_broadcast(&w->changed);
        pthread_mutex_unlock(&w->mutex);
    }
}

static double seconds(void) {
    struct timespec now;
    clock_gettime(CLOCK_MONOTONIC, &now);
    return (double)now.tv_sec + 1e-9 * (double)now.tv_nsec;
}

/* Wait until the state is one of a or b: poll (yielding the core) for spin [s], then sleep. */
static int await_state(Worker *w, int a, int b, double spin) {
    int s = state_of(w);
    if (s == a || s == b) return s;
    if (spin > 0.0) {
        const double until = seconds() + spin;
        do {
            sched_yield();
            s = state_of(w);
            if (s == a || s == b) return s;
        } while (seconds() < until);
    }
    pthread_mutex_lock(&w->mutex);
    __atomic_add_fetch(&w->sleepers, 1, __ATOMIC_SEQ_CST);
    while ((s = state_of(w)) != a && s != b) pthread_cond_wait(&w->changed, &w->mutex);
    __atomic_sub_fetch(&w->sleepers, 1, __ATOMIC_SEQ_CST);
    pthread_mutex_unlock(&w->mutex);
    return s;
}

static void *work(void *arg) {
    Worker *w = arg;
    while (await_state(w, PENDING, QUIT, w->spin) == PENDING) {
        const Job *j = w->job;
        w->result = advance(j->plan, j->values, j->k_begin, j->k_end, j->h, j->sample_ticks,
                            j->n_samples, j->samples, j->n_values, &w->ticks_done, &w->failure);
        publish(w, DONE);
    }
    return NULL;
}

/* A worker thread, idle, for the jobs written into *job; NULL if no thread could be started. */
EXPORT Worker *softhil_worker_new(double spin, const Job *job) {
    Worker *w = calloc(1, sizeof(Worker));
    if (w == NULL) return NULL;
    w->job = job;
    w->spin = spin;
    w->state = IDLE;
    if (pthread_mutex_init(&w->mutex, NULL) != 0) {
        free(w);
        return NULL;
    }
    if (pthread_cond_init(&w->changed, NULL) != 0) {
        pthread_mutex_destroy(&w->mutex);
        free(w);
        return NULL;
    }
    if (pthread_create(&w->thread, NULL, work, w) != 0) {
        pthread_cond_destroy(&w->changed);
        pthread_mutex_destroy(&w->mutex);
        free(w);
        return NULL;
    }
#ifdef __linux__
    pthread_setname_np(w->thread, "softhil-kernel"); /* as ps and top show it */
#endif
    return w;
}

/* Start the job (the worker must be idle: no job, or the last one waited for): stepping ticks
 * k_begin .. k_end - 1 as softhil_advance does, sampling values[] at the sample ticks
 * (ascending, within the range) into samples (n_samples rows of n_values). */
EXPORT void softhil_worker_go(Worker *w) { publish(w, PENDING); }

/* Wait for the started job; its outcome as softhil_advance's. The worker is idle again. */
EXPORT int softhil_worker_wait(Worker *w, long long *ticks_done, Failure *failure) {
    await_state(w, DONE, DONE, w->spin);
    *ticks_done = w->ticks_done;
    *failure = w->failure;
    __atomic_store_n(&w->state, IDLE, __ATOMIC_SEQ_CST); /* nobody waits for IDLE */
    return w->result;
}

/* Stop the thread and free the worker; a job still running is waited for first (its QUIT
 * would otherwise be overwritten by the job's DONE, and the thread never end). */
EXPORT void softhil_worker_free(Worker *w) {
    if (w == NULL) return;
    if (state_of(w) == PENDING) await_state(w, DONE, DONE, 0.0);
    publish(w, QUIT);
    pthread_join(w->thread, NULL);
    pthread_cond_destroy(&w->changed);
    pthread_mutex_destroy(&w->mutex);
    free(w);
}
