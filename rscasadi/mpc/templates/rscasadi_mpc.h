/* rscasadi MPC for ${model} (${n} joints): multiple shooting, Gauss-Newton SQP (${iters}), generated
 * by rscasadi mpc.  The controller's state is the caller's ${mpc}_t (no allocation, no static data:
 * any number of controllers in one process, one thread each).  ${mpc}_init once with the measured
 * state, then ${mpc}_step (or ${mpc}_step_to) every ${ts} s.
 * x: theta, phi, dtheta, dphi (${nx}); reference: ${nref} values, column-major ${rows} x N, a column
 * per interval end t + k * ${h} s, k = 1..${N}: ${reference}; target (${mpc}_step_to, held):
 * ${target}; tau_out: ${n} motor torques, always finite and within the limits
 * (${tau_limits} N m).
 *
 * Failure policy (rscasadi_guard.h).  ${mpc}_init refuses a measurement outside the box below
 * (${MPC}_BAD_MEASUREMENT) and leaves the controller uninitialised: ${mpc}_step before a successful init
 * returns ${MPC}_NOT_INITIALISED with zero torques.  ${mpc}_step returns 0 on success, else a code, and
 * then tau_out is the holding torque of the last good measured state (the motor torques that hold
 * the motors still there, within the limits):
 *   ${MPC}_BAD_MEASUREMENT  x_measured not finite or outside [${x_lo}]
 *                        .. [${x_hi}] (theta, phi, dtheta, dphi); the plan is kept;
 *   ${MPC}_BAD_REFERENCE    a reference (or target) value not finite or outside, row by row,
 *                        [${ref_lo}] .. [${ref_hi}]; the plan is kept;
 *   ${MPC}_NOT_FINITE       the new plan is not finite, ${MPC}_FAILED the generated function failed:
 *                        the plan restarts from the arm held at the measured state.
 * The next good sample is acted on as usual, without a re-init.  ${MPC}_BAD_ARGUMENT: a NULL array,
 * or a setter's value refused (nothing is changed).
 *
 * ${mpc}_step_seconds: the duration of the last ${mpc}_step or ${mpc}_step_to (CLOCK_MONOTONIC).
 * ${mpc}_set_payload_mass: the payload's mass (kg) from the next step on (${MPC}_NO_PAYLOAD if the model
 * holds none); ${mpc}_set_parameters: the arm's ${MPC}_NP parameters from the next step on (names in
 * manifest.json: a parametric = "family" controller takes every parameter not zero in its model,
 * e.g. an identified arm's); ${mpc}_init_parameters: ${mpc}_init with them (the first plan holds that
 * arm); ${mpc}_set_posture: the link angles a redundant arm's null space is held near in task space
 * (${mpc}_init sets the measured ones and the model's parameters). */
#ifndef ${MPC}_H
#define ${MPC}_H
#include <stddef.h>
#define ${MPC}_NX ${nx}
#define ${MPC}_NU ${n}
#define ${MPC}_HORIZON ${N}
#define ${MPC}_NREF ${nref}
#define ${MPC}_NTARGET ${ntarget}
#define ${MPC}_NPARAMS ${nparams}
#define ${MPC}_NP ${np}
#define ${MPC}_TASK_SPACE ${task}
#define ${MPC}_NOT_FINITE 2
#define ${MPC}_FAILED 3
#define ${MPC}_NO_PAYLOAD 4
#define ${MPC}_BAD_ARGUMENT 5
#define ${MPC}_BAD_MEASUREMENT 6
#define ${MPC}_BAD_REFERENCE 7
#define ${MPC}_NOT_INITIALISED 8
typedef struct ${mpc}_s {
  double X[${MPC}_NX * (${MPC}_HORIZON + 1)], U[${MPC}_NU * ${MPC}_HORIZON];
  double X_next[${MPC}_NX * (${MPC}_HORIZON + 1)], U_next[${MPC}_NU * ${MPC}_HORIZON];
  double target_reference[${MPC}_NREF];
  double params[${MPC}_NPARAMS + 1];         /* the posture, then the arm's parameters (${MPC}_NP) */
  double x_good[${MPC}_NX];                  /* the last measured state acted on */
  double w[${sz_w}];
  long long iw[${sz_iw}];
  double last_step_seconds;
  int ready;                              /* RSCASADI_READY after a successful init */
} ${mpc}_t;
size_t ${mpc}_sizeof(void);
int ${mpc}_init(${mpc}_t *c, const double *x_measured);
int ${mpc}_init_parameters(${mpc}_t *c, const double *x_measured, const double *p);
int ${mpc}_step(${mpc}_t *c, const double *x_measured, const double *reference, double *tau_out);
int ${mpc}_step_to(${mpc}_t *c, const double *x_measured, const double *target, double *tau_out);
double ${mpc}_step_seconds(const ${mpc}_t *c);
int ${mpc}_set_payload_mass(${mpc}_t *c, double mass);
int ${mpc}_set_parameters(${mpc}_t *c, const double *p);
int ${mpc}_set_posture(${mpc}_t *c, const double *theta);
#endif
