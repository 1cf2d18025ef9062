/* rscasadi MPC for ${model} (${n} joints): multiple shooting, Gauss-Newton SQP (${iters}), generated
 * by rscasadi mpc.  The controller's state is the caller's mpc_t (no allocation, no static data:
 * any number of controllers in one process, one thread each).  mpc_init once with the measured
 * state, then mpc_step (or mpc_step_to) every ${ts} s.
 * x: theta, phi, dtheta, dphi (${nx}); reference: ${nref} values, column-major ${rows} x N, a column
 * per interval end t + k * ${h} s, k = 1..${N}: ${reference}; target (mpc_step_to, held):
 * ${target}; tau_out: ${n} motor torques, always finite and within the limits
 * (${tau_limits} N m).
 *
 * Failure policy (rscasadi_guard.h).  mpc_init refuses a measurement outside the box below
 * (MPC_BAD_MEASUREMENT) and leaves the controller uninitialised: mpc_step before a successful init
 * returns MPC_NOT_INITIALISED with zero torques.  mpc_step returns 0 on success, else a code, and
 * then tau_out is the holding torque of the last good measured state (the motor torques that hold
 * the motors still there, within the limits):
 *   MPC_BAD_MEASUREMENT  x_measured not finite or outside [${x_lo}]
 *                        .. [${x_hi}] (theta, phi, dtheta, dphi); the plan is kept;
 *   MPC_BAD_REFERENCE    a reference (or target) value not finite or outside, row by row,
 *                        [${ref_lo}] .. [${ref_hi}]; the plan is kept;
 *   MPC_NOT_FINITE       the new plan is not finite, MPC_FAILED the generated function failed:
 *                        the plan restarts from the arm held at the measured state.
 * The next good sample is acted on as usual, without a re-init.  MPC_BAD_ARGUMENT: a NULL array,
 * or a setter's value refused (nothing is changed).
 *
 * mpc_step_seconds: the duration of the last mpc_step or mpc_step_to (CLOCK_MONOTONIC).
 * mpc_set_payload_mass: the payload's mass (kg) from the next step on (MPC_NO_PAYLOAD if the model
 * holds none); mpc_set_parameters: the arm's MPC_NP parameters from the next step on (names in
 * manifest.json: a parametric = "family" controller takes every parameter not zero in its model,
 * e.g. an identified arm's); mpc_init_parameters: mpc_init with them (the first plan holds that
 * arm); mpc_set_posture: the link angles a redundant arm's null space is held near in task space
 * (mpc_init sets the measured ones and the model's parameters). */
#ifndef RSCASADI_MPC_H
#define RSCASADI_MPC_H
#include <stddef.h>
#define MPC_NX ${nx}
#define MPC_NU ${n}
#define MPC_HORIZON ${N}
#define MPC_NREF ${nref}
#define MPC_NTARGET ${ntarget}
#define MPC_NPARAMS ${nparams}
#define MPC_NP ${np}
#define MPC_TASK_SPACE ${task}
#define MPC_NOT_FINITE 2
#define MPC_FAILED 3
#define MPC_NO_PAYLOAD 4
#define MPC_BAD_ARGUMENT 5
#define MPC_BAD_MEASUREMENT 6
#define MPC_BAD_REFERENCE 7
#define MPC_NOT_INITIALISED 8
typedef struct mpc_s {
  double X[MPC_NX * (MPC_HORIZON + 1)], U[MPC_NU * MPC_HORIZON];
  double X_next[MPC_NX * (MPC_HORIZON + 1)], U_next[MPC_NU * MPC_HORIZON];
  double target_reference[MPC_NREF];
  double params[MPC_NPARAMS + 1];         /* the posture, then the arm's parameters (MPC_NP) */
  double x_good[MPC_NX];                  /* the last measured state acted on */
  double w[${sz_w}];
  long long iw[${sz_iw}];
  double last_step_seconds;
  int ready;                              /* RSCASADI_READY after a successful init */
} mpc_t;
size_t mpc_sizeof(void);
int mpc_init(mpc_t *c, const double *x_measured);
int mpc_init_parameters(mpc_t *c, const double *x_measured, const double *p);
int mpc_step(mpc_t *c, const double *x_measured, const double *reference, double *tau_out);
int mpc_step_to(mpc_t *c, const double *x_measured, const double *target, double *tau_out);
double mpc_step_seconds(const mpc_t *c);
int mpc_set_payload_mass(mpc_t *c, double mass);
int mpc_set_parameters(mpc_t *c, const double *p);
int mpc_set_posture(mpc_t *c, const double *theta);
#endif
