/* rscasadi MPC for ${model} (${n} joints): multiple shooting, Gauss-Newton SQP (${iters}), generated
 * by rscasadi mpc.  The controller's state is the caller's ${sym}_t (no allocation, no static data:
 * any number of controllers in one process, one thread each).  ${sym}_init once with the measured
 * state, then ${sym}_step (or ${sym}_step_to) every ${ts} s.
 * x: theta, phi, dtheta, dphi (${nx}); reference: ${nref} values, column-major ${rows} x N, a column
 * per interval end t + k * ${h} s, k = 1..${N}: ${reference}; target (${sym}_step_to, held):
 * ${target}; tau_out: ${nu} motor torques (the actuated joints'), always finite and within the limits
 * (${tau_limits} N m).
 *
 * Failure policy (rscasadi_guard.h).  ${sym}_init refuses a measurement outside the box below
 * (${SYM}_BAD_MEASUREMENT) and leaves the controller uninitialised: ${sym}_step before a successful init
 * returns ${SYM}_NOT_INITIALISED with zero torques.  ${sym}_step returns 0 on success, else a code, and
 * then tau_out is the holding torque of the last good measured state (the motor torques that hold
 * the motors still there, within the limits):
 *   ${SYM}_BAD_MEASUREMENT  x_measured not finite or outside [${x_lo}]
 *                        .. [${x_hi}] (theta, phi, dtheta, dphi); the plan is kept;
 *   ${SYM}_BAD_REFERENCE    a reference (or target) value not finite or outside, row by row,
 *                        [${ref_lo}] .. [${ref_hi}]; the plan is kept;
 *   ${SYM}_NOT_FINITE       the new plan is not finite, ${SYM}_FAILED the generated function failed:
 *                        the plan restarts from the arm held at the measured state.
 * The next good sample is acted on as usual, without a re-init.  ${SYM}_BAD_ARGUMENT: a NULL array,
 * or a setter's value refused (nothing is changed).
 *
 * Split real-time iteration: ${sym}_step is ${sym}_prepare then ${sym}_feedback.  ${sym}_prepare(c,
 * reference) does all that needs no measurement (the linearisation at the shifted plan and the
 * condensed QP, with the measured state's effect kept affine); call it after a step, while
 * waiting for the next sample.  ${sym}_feedback(c, x_measured, tau_out) then solves that QP from
 * the measurement: the measurement-to-torque latency.  A feedback without a prepare since the
 * last one returns ${SYM}_NOT_PREPARED (and the holding torque); one after a refused prepare
 * returns the prepare's code.  With more than one SQP iteration the prepare only keeps the
 * reference and the feedback does the whole step.
 *
 * QP: ${qp}.  With the Riccati recursion (${SYM}_RICCATI 1: HPIPM, linked from CasADi's
 * installation) the prepare forms each interval's QP (dynamics, cost) and the feedback solves it
 * from the measured state; HPIPM's structures live in the controller's own memory, placed at
 * the first prepare: a controller moved (copied) after that re-places them at its next prepare,
 * and a feedback before it returns ${SYM}_NOT_PREPARED.
 *
 * ${sym}_step_seconds: the duration of the last ${sym}_step or ${sym}_step_to (CLOCK_MONOTONIC);
 * ${sym}_feedback_seconds: of the last ${sym}_feedback (within a step too).
 * ${sym}_set_payload_mass: the payload's mass (kg) from the next step on (${SYM}_NO_PAYLOAD if the model
 * holds none); ${sym}_set_parameters: the arm's ${SYM}_NP parameters from the next step on (names in
 * manifest.json: a parametric = "family" controller takes every parameter not zero in its model,
 * e.g. an identified arm's); ${sym}_init_parameters: ${sym}_init with them (the first plan holds that
 * arm); ${sym}_set_posture: the link angles a redundant arm's null space is held near in task space
 * (${sym}_init sets the measured ones and the model's parameters). */
#ifndef ${SYM}_H
#define ${SYM}_H
#include <stddef.h>
#define ${SYM}_NX ${nx}
#define ${SYM}_NU ${nu}
#define ${SYM}_NJ ${n}
#define ${SYM}_HORIZON ${N}
#define ${SYM}_NREF ${nref}
#define ${SYM}_NTARGET ${ntarget}
#define ${SYM}_NFRAMES ${nframes}      /* task space: the frames followed, a reference block each */
#define ${SYM}_NPARAMS ${nparams}
#define ${SYM}_NP ${np}
#define ${SYM}_TASK_SPACE ${task}
#define ${SYM}_NOT_FINITE 2
#define ${SYM}_FAILED 3
#define ${SYM}_NO_PAYLOAD 4
#define ${SYM}_BAD_ARGUMENT 5
#define ${SYM}_BAD_MEASUREMENT 6
#define ${SYM}_BAD_REFERENCE 7
#define ${SYM}_NOT_INITIALISED 8
#define ${SYM}_NOT_PREPARED 9
#define ${SYM}_SPLIT ${split}              /* 1: prepare does the linearisation (real-time iteration) */
#define ${SYM}_RICCATI ${riccati}            /* 1: the QP by HPIPM's Riccati recursion on the stages */
#define ${SYM}_THREADS ${threads}            /* the Riccati preparation's loops over the intervals on this
                                           many threads (OpenMP, when compiled with it) */
typedef struct ${sym}_s {
  double X[${SYM}_NX * (${SYM}_HORIZON + 1)], U[${SYM}_NU * ${SYM}_HORIZON];
  double X_next[${SYM}_NX * (${SYM}_HORIZON + 1)], U_next[${SYM}_NU * ${SYM}_HORIZON];
  double target_reference[${SYM}_NREF];
  double params[${SYM}_NPARAMS + 1];         /* the posture, then the arm's parameters (${SYM}_NP) */
  double x_good[${SYM}_NX];                  /* the last measured state acted on */
  double prep[${nprep}];                  /* the prepared QP (manifest.json: prepared) */
  double reference[${SYM}_NREF];           /* the prepared reference (more than one SQP iteration) */
  long long qp_memory[${qp_words}];        /* HPIPM's structures and work (${SYM}_RICCATI) */
  double first[${nfirst}];                /* the first interval's A, S, b, r (${SYM}_RICCATI) */
  double lin[${nlin}];                    /* each interval's step x_{k+1}, A, B, then the gaps e_k (${SYM}_RICCATI) */
  const void *qp_owner;                   /* the controller they were placed for */
  double w[${SYM}_THREADS * ${sz_w}];     /* CasADi's work arrays, one part per thread */
  long long iw[${SYM}_THREADS * ${sz_iw}];
  double last_step_seconds, last_feedback_seconds;
  int prepared;                           /* RSCASADI_READY: prepared; else 0 or the prepare's code */
  int ready;                              /* RSCASADI_READY after a successful init */
} ${sym}_t;
size_t ${sym}_sizeof(void);
int ${sym}_init(${sym}_t *c, const double *x_measured);
int ${sym}_init_parameters(${sym}_t *c, const double *x_measured, const double *p);
int ${sym}_step(${sym}_t *c, const double *x_measured, const double *reference, double *tau_out);
int ${sym}_step_to(${sym}_t *c, const double *x_measured, const double *target, double *tau_out);
int ${sym}_prepare(${sym}_t *c, const double *reference);
int ${sym}_feedback(${sym}_t *c, const double *x_measured, double *tau_out);
double ${sym}_feedback_seconds(const ${sym}_t *c);
double ${sym}_step_seconds(const ${sym}_t *c);
int ${sym}_set_payload_mass(${sym}_t *c, double mass);
int ${sym}_set_parameters(${sym}_t *c, const double *p);
int ${sym}_set_posture(${sym}_t *c, const double *theta);
#endif
