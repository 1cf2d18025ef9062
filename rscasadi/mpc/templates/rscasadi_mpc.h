/* rscasadi MPC for ${model} (${n} joints): multiple shooting, Gauss-Newton SQP (${iters}), generated
 * by rscasadi mpc.  mpc_init once with the measured state, then mpc_step (or mpc_step_to) every
 * ${ts} s.  No allocation; not reentrant (one controller per process: its plan is static).
 * x: theta, phi, dtheta, dphi (${nx}); reference: ${nref} values, column-major 2n x N: theta_ref
 * then dtheta_ref at t + k * ${h} s, k = 1..${N}; theta_target: ${n} link angles (a pose to reach
 * and hold); tau_out: ${n} motor torques.  Return 0 on success; MPC_NOT_FINITE if the new plan
 * is not finite (e.g. a NaN in x_measured or reference), MPC_FAILED if the generated function
 * failed: then the plan is kept and tau_out is its first torque (within the limits).
 * mpc_step_seconds: the duration of the last mpc_step or mpc_step_to (CLOCK_MONOTONIC). */
#ifndef RSCASADI_MPC_H
#define RSCASADI_MPC_H
#define MPC_NX ${nx}
#define MPC_NU ${n}
#define MPC_HORIZON ${N}
#define MPC_NREF ${nref}
#define MPC_NOT_FINITE 2
#define MPC_FAILED 3
int mpc_init(const double *x_measured);
int mpc_step(const double *x_measured, const double *reference, double *tau_out);
int mpc_step_to(const double *x_measured, const double *theta_target, double *tau_out);
double mpc_step_seconds(void);
#endif
