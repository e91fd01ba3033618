/* The physical limit for bench/bench_run.py: N planar-arm segments (DriveCylinder + FeaSegment)
 * stepped with their coupling in one C loop, with no Python and no master in it. The FMU
 * instances are the ones fmpy loaded and initialised; the caller passes their FMI function
 * pointers and component handles. Per tick and segment: fmi2SetReal (cylinder p_a, p_b; segment
 * x_piston), fmi2DoStep of both, fmi2GetReal (cylinder x; segment p_a, p_b): Jacobi, as the
 * master. Returns 0, or the failing FMI status. */
#include <stddef.h>

typedef int (*SetReal)(void *, const unsigned int[], size_t, const double[]);
typedef int (*GetReal)(void *, const unsigned int[], size_t, double[]);
typedef int (*DoStep)(void *, double, double, int);

typedef struct {
    void *cylinder, *segment;
    void *cyl_set, *cyl_get, *cyl_step, *seg_set, *seg_get, *seg_step;
    unsigned int cyl_p[2], cyl_x, seg_x, seg_p[2];
} Segment;

__attribute__((visibility("default"))) int pure_loop(Segment *segments, int n, long long ticks,
                                                     double h) {
    double x[64], p[64][2];
    if (n > 64) return -1;
    for (int i = 0; i < n; ++i) {
        Segment *s = &segments[i];
        int status = ((GetReal)s->cyl_get)(s->cylinder, &s->cyl_x, 1, &x[i]);
        status |= ((GetReal)s->seg_get)(s->segment, s->seg_p, 2, p[i]);
        if (status > 1) return status;
    }
    for (long long k = 0; k < ticks; ++k) {
        for (int i = 0; i < n; ++i) {
            Segment *s = &segments[i];
            int status = ((SetReal)s->cyl_set)(s->cylinder, s->cyl_p, 2, p[i]);
            if (status > 1) return status;
            status = ((SetReal)s->seg_set)(s->segment, &s->seg_x, 1, &x[i]);
            if (status > 1) return status;
            status = ((DoStep)s->cyl_step)(s->cylinder, (double)k * h, h, 1);
            if (status > 1) return status;
            status = ((DoStep)s->seg_step)(s->segment, (double)k * h, h, 1);
            if (status > 1) return status;
        }
        for (int i = 0; i < n; ++i) {
            Segment *s = &segments[i];
            int status = ((GetReal)s->cyl_get)(s->cylinder, &s->cyl_x, 1, &x[i]);
            if (status > 1) return status;
            status = ((GetReal)s->seg_get)(s->segment, s->seg_p, 2, p[i]);
            if (status > 1) return status;
        }
    }
    return 0;
}
