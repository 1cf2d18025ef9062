/* The input guard every rscasadi controller applies before it acts, and the one failure policy
 * they share (their headers state it):
 *   - a controller acts only after a successful *_init (its state carries RSCASADI_READY); before,
 *     *_step returns *_NOT_INITIALISED and zero torques;
 *   - a measurement, reference, target or gain outside its stated box (NaN and infinity are outside
 *     every box) is refused with a code, and the output is the safe one its header names (the
 *     holding torque of the last good state, within the limits), never NaN, never beyond a limit;
 *   - the controller is not changed by a refused sample: the next good one is acted on as usual.
 * Also the clock their *_step_seconds read.
 * Everything here is static, so any number of generated controllers link into one binary. */
#ifndef RSCASADI_GUARD_H
#define RSCASADI_GUARD_H
#include <math.h>

#define RSCASADI_READY 0x52534341          /* "RSCA": set by a successful init, cleared by a failed one */

#if defined(_POSIX_C_SOURCE) && _POSIX_C_SOURCE >= 199309L   /* the controllers' sources, not their users */
#include <time.h>
/* seconds on CLOCK_MONOTONIC: a step's duration is the difference of two readings */
static inline double rscasadi_now(void) {
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return t.tv_sec + 1e-9 * t.tv_nsec;
}
#endif

/* 1 if lo[i] <= v[i] <= hi[i] for every i (a NaN fails every comparison); 0 for a NULL array */
static inline int rscasadi_within(const double *v, const double *lo, const double *hi, int n) {
  if (!v) return 0;
  for (int i = 0; i < n; ++i)
    if (!(v[i] >= lo[i] && v[i] <= hi[i])) return 0;
  return 1;
}

/* tau within +-limit (INFINITY: none); a value that is not finite becomes 0 */
static inline void rscasadi_clamp(double *tau, const double *limit, int n) {
  for (int i = 0; i < n; ++i) {
    double t = isfinite(tau[i]) ? tau[i] : 0.0;
    tau[i] = t > limit[i] ? limit[i] : (t < -limit[i] ? -limit[i] : t);
  }
}

static inline void rscasadi_zero(double *v, int n) {
  for (int i = 0; i < n; ++i) v[i] = 0.0;
}
#endif
