/* The four generated controllers (joint-space MPC, joint-space impedance, observer, the arm
 * library's guarded feedforward) of one arm
 * linked into one binary and fed what a broken sensor, a buggy caller or garbage memory gives:
 * NULL arrays, an uninitialised state, NaN, infinities and absurd numbers in every input.
 * Every output must be finite, every code the one the headers promise, and (run under valgrind
 * by tests/test_controller_safety.py) no read or write may leave the caller's arrays.
 * Prints "N passed, M failed" and exits 1 on a failure. */
#include <math.h>
#include <stdio.h>
#include <string.h>
#include "rscasadi_mpc.h"
#include "rscasadi_impedance.h"
#include "rscasadi_observer.h"
#include "rscasadi_feedforward.h"

#define N MPC_NU
static int passed = 0, failed = 0;
static mpc_t mpc;
static impedance_t imp;
static observer_t obs;
static ff_t ff;

static void check(int ok, const char *what, int i) {
  if (ok) ++passed;
  else {
    ++failed;
    fprintf(stderr, "FAILED: %s (entry %d)\n", what, i);
  }
}

static int finite_all(const double *v, int n) {
  for (int i = 0; i < n; ++i)
    if (!isfinite(v[i])) return 0;
  return 1;
}

static const double BAD[] = {NAN, INFINITY, -INFINITY, 1e300, -1e300, 1e3};   /* 1e3 rad, rad/s: absurd */
#define NBAD (int)(sizeof BAD / sizeof BAD[0])

int main(void) {
  double x[4 * N] = {0}, ref[MPC_NREF] = {0}, tau[N], r[OBSERVER_NQ], q_d[N] = {0}, k[N], z[N], t_applied[N] = {0};
  for (int i = 0; i < N; ++i) k[i] = 50.0, z[i] = 0.7;

  /* garbage memory: every step refuses with NOT_INITIALISED and zeros */
  memset(&mpc, 0xAB, sizeof mpc);
  memset(&imp, 0xAB, sizeof imp);
  memset(&obs, 0xAB, sizeof obs);
  memset(&ff, 0xAB, sizeof ff);
  check(ff_step(&ff, q_d, q_d, q_d, 1e-3, tau) == FF_NOT_INITIALISED && tau[0] == 0.0, "feedforward before init", 0);
  check(ff_step(&ff, q_d, q_d, q_d, 1e-3, NULL) == FF_BAD_ARGUMENT && ff_init(NULL, q_d, q_d, q_d, tau) == FF_BAD_ARGUMENT,
        "feedforward NULL", 0);
  check(ff_init(&ff, NULL, q_d, q_d, tau) == FF_BAD_REFERENCE, "feedforward NULL sample", 0);
  for (int i = 0; i < N; ++i) tau[i] = 7.0;
  check(mpc_step(&mpc, x, ref, tau) == MPC_NOT_INITIALISED && tau[0] == 0.0, "mpc before init", 0);
  check(impedance_step(&imp, x, q_d, k, z, tau) == IMPEDANCE_NOT_INITIALISED && tau[0] == 0.0, "impedance before init", 0);
  check(observer_step(&obs, x, t_applied, r) == OBSERVER_NOT_INITIALISED && r[0] == 0.0, "observer before init", 0);
  check(mpc_step(NULL, x, ref, tau) == MPC_NOT_INITIALISED && mpc_step_to(NULL, x, q_d, tau) == MPC_NOT_INITIALISED,
        "mpc NULL state", 0);
  check(mpc_step(&mpc, x, ref, NULL) == MPC_BAD_ARGUMENT && impedance_step(&imp, x, q_d, k, z, NULL) == IMPEDANCE_BAD_ARGUMENT
        && observer_step(&obs, x, t_applied, NULL) == OBSERVER_BAD_ARGUMENT, "NULL outputs", 0);
  check(mpc_init(NULL, x) == MPC_BAD_ARGUMENT && impedance_init(NULL, x) == IMPEDANCE_BAD_ARGUMENT
        && observer_init(NULL, x) == OBSERVER_BAD_ARGUMENT, "NULL states at init", 0);

  /* an init with a bad measurement leaves the controller uninitialised */
  for (int i = 0; i < 4 * N; ++i)
    for (int b = 0; b < NBAD; ++b) {
      double bad[4 * N];
      memcpy(bad, x, sizeof bad);
      bad[i] = BAD[b];
      check(mpc_init(&mpc, bad) == MPC_BAD_MEASUREMENT, "mpc_init refuses", i);
      check(mpc_step(&mpc, x, ref, tau) == MPC_NOT_INITIALISED, "mpc after a refused init", i);
      check(impedance_init(&imp, bad) == IMPEDANCE_BAD_MEASUREMENT, "impedance_init refuses", i);
      check(observer_init(&obs, bad) == OBSERVER_BAD_MEASUREMENT, "observer_init refuses", i);
    }
  check(mpc_init(&mpc, NULL) == MPC_BAD_MEASUREMENT, "mpc_init NULL x", 0);

  check(mpc_init(&mpc, x) == 0 && impedance_init(&imp, x) == 0 && observer_init(&obs, x) == 0
        && ff_init(&ff, q_d, q_d, q_d, tau) == 0, "init", 0);
  check(mpc_step(&mpc, x, ref, tau) == 0 && finite_all(tau, N), "mpc good step", 0);

  /* every entry of every input, every bad value: the promised code, finite outputs, and the next
     good sample is acted on */
  for (int b = 0; b < NBAD; ++b) {
    for (int i = 0; i < 4 * N; ++i) {
      double bad[4 * N];
      memcpy(bad, x, sizeof bad);
      bad[i] = BAD[b];
      check(mpc_step(&mpc, bad, ref, tau) == MPC_BAD_MEASUREMENT && finite_all(tau, N), "mpc x", i);
      check(impedance_step(&imp, bad, q_d, k, z, tau) == IMPEDANCE_BAD_MEASUREMENT && finite_all(tau, N), "impedance x", i);
      check(observer_step(&obs, bad, t_applied, r) == OBSERVER_BAD_MEASUREMENT && finite_all(r, OBSERVER_NQ), "observer x", i);
    }
    for (int i = 0; i < MPC_NREF; ++i) {
      double bad[MPC_NREF];
      memcpy(bad, ref, sizeof bad);
      bad[i] = BAD[b];
      check(mpc_step(&mpc, x, bad, tau) == MPC_BAD_REFERENCE && finite_all(tau, N), "mpc reference", i);
    }
    for (int i = 0; i < N; ++i) {
      double bq[N], bk[N], bz[N], bt[N];
      memcpy(bq, q_d, sizeof bq), memcpy(bk, k, sizeof bk), memcpy(bz, z, sizeof bz), memcpy(bt, t_applied, sizeof bt);
      bq[i] = bk[i] = bz[i] = BAD[b] * (b == NBAD - 1 ? 1e6 : 1.0);     /* 1e9: beyond every box */
      bt[i] = BAD[b] * (b == NBAD - 1 ? 1e6 : 1.0);
      check(mpc_step_to(&mpc, x, bq, tau) == MPC_BAD_REFERENCE && finite_all(tau, N), "mpc target", i);
      check(impedance_step(&imp, x, bq, k, z, tau) == IMPEDANCE_BAD_REFERENCE && finite_all(tau, N), "impedance reference", i);
      check(impedance_step(&imp, x, q_d, bk, z, tau) == IMPEDANCE_BAD_REFERENCE && finite_all(tau, N), "impedance stiffness", i);
      check(impedance_step(&imp, x, q_d, k, bz, tau) == IMPEDANCE_BAD_REFERENCE && finite_all(tau, N), "impedance damping", i);
      check(observer_step(&obs, x, bt, r) == OBSERVER_BAD_TORQUE && finite_all(r, OBSERVER_NQ), "observer torque", i);
      check(ff_step(&ff, bq, q_d, q_d, 1e-3, tau) == FF_BAD_REFERENCE && finite_all(tau, N), "feedforward theta", i);
      check(ff_step(&ff, q_d, bq, q_d, 1e-3, tau) == FF_BAD_REFERENCE && finite_all(tau, N), "feedforward speed", i);
      check(ff_step(&ff, q_d, q_d, bq, 1e-3, tau) == FF_BAD_REFERENCE && finite_all(tau, N), "feedforward acceleration", i);
    }
    check(mpc_step(&mpc, x, NULL, tau) == MPC_BAD_REFERENCE && mpc_step(&mpc, NULL, ref, tau) == MPC_BAD_MEASUREMENT,
          "mpc NULL inputs", b);
    check(mpc_step(&mpc, x, ref, tau) == 0 && finite_all(tau, N), "mpc recovers", b);
    check(impedance_step(&imp, x, q_d, k, z, tau) == 0 && finite_all(tau, N), "impedance recovers", b);
    check(observer_step(&obs, x, t_applied, r) <= OBSERVER_COLLISION && finite_all(r, OBSERVER_NQ), "observer recovers", b);
    check(ff_step(&ff, q_d, q_d, q_d, BAD[b], tau) == FF_BAD_REFERENCE && finite_all(tau, N), "feedforward h", b);
    check(ff_step(&ff, q_d, q_d, q_d, 1e-3, tau) == 0 && finite_all(tau, N), "feedforward recovers", b);
  }
  printf("%d passed, %d failed\n", passed, failed);
  return failed != 0;
}
