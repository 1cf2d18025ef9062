/* rscasadi MPC for ${model} (${n} joints): multiple shooting, Gauss-Newton SQP (${iters}), generated
 * by rscasadi mpc.  The controller's state is the caller's mpc_t (no allocation, no static data:
 * any number of controllers in one process, one thread each).  mpc_init once with the measured
 * state, then mpc_step (or mpc_step_to) every ${ts} s.
 * x: theta, phi, dtheta, dphi (${nx}); reference: ${nref} values, column-major ${rows} x N, a column
 * per interval end t + k * ${h} s, k = 1..${N}: ${reference}; target (mpc_step_to, held):
 * ${target}; tau_out: ${n} motor torques.  Return 0 on success; MPC_NOT_FINITE if the new plan is
 * not finite (e.g. a NaN in x_measured or reference), MPC_FAILED if the generated function failed:
 * then the plan is kept and tau_out is its first torque (within the limits).
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
typedef struct mpc_s {
  double X[MPC_NX * (MPC_HORIZON + 1)], U[MPC_NU * MPC_HORIZON];
  double X_next[MPC_NX * (MPC_HORIZON + 1)], U_next[MPC_NU * MPC_HORIZON];
  double target_reference[MPC_NREF];
  double params[MPC_NPARAMS + 1];         /* the posture, then the arm's parameters (MPC_NP) */
  double w[${sz_w}];
  long long iw[${sz_iw}];
  double last_step_seconds;
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
