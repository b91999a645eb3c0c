/* lfm_controller.h: the exported scenario MPC controller of one system and agent.

   Written by lfm-export (lfm-scenario-mpc) with lfm_config.h, lfm_config.c and lfm_mpc.c
   beside it; needs nothing but the C library and libm. The controller is the agent of the
   exported config: its horizon LFM_N, its LFM_NS scenarios, its cost, constraints, solver
   options and estimator, as numbers in lfm_config.c. One controller serves one robot; it
   allocates its memory in lfm_controller_new and nothing after that but the solver's own
   scratch inside each solve (see docs/export.md).

   Units are the system's (lfm_config.h names the states and inputs). Arrays are row-major:
     x0     (LFM_NX)                   a state
     W      (LFM_NS, LFM_N, LFM_NW)    the latent force of every scenario and step
     plan   (LFM_N, LFM_NU)            the input sequence
     y      (LFM_NX)                   a measurement of the state, y = x + e

   A typical loop (every call of lfm_controller_step writes u, whatever it returns):
     lfm_controller* c = lfm_controller_new();
     lfm_controller_reset(c, seed);
     for (;;) { read y; lfm_controller_step(c, y, u); apply u; }
     lfm_controller_free(c);

   Bad input: a NaN or infinite number in y (a sensor fault), x0 or W gives LFM_BAD_INPUT,
   and u (every stage of the plan, for lfm_controller_solve) is the system's fallback input
   (fallback_input in lfm_config.c), with lfm_info.action LFM_FROM_FALLBACK; the UKF's
   estimate is carried one step ahead without the measurement, and the last plan is dropped.
   An agent whose step is not exported (LFM_NO_STEP) gets the fallback input the same way. */
#ifndef LFM_CONTROLLER_H
#define LFM_CONTROLLER_H

#include <stdint.h>

#include "lfm_config.h"

#ifdef __cplusplus
extern "C" {
#endif

typedef struct lfm_controller lfm_controller;

/* Statuses: those of the solver (>= 0; LFM_SOLVED and LFM_ACCEPTABLE are successes, the
   others say why the plan is not converged; lfm_status_name names each) and errors (< 0). */
#define LFM_SOLVED 0
#define LFM_ACCEPTABLE 1
#define LFM_NO_STEP (-1)      /* the agent's estimator is not exported: use lfm_controller_solve */
#define LFM_BAD_INPUT (-2)    /* a NaN or infinite number in the arguments: u is the fallback */
#define LFM_OUT_OF_MEMORY (-3)

/* Where the last step's input came from. */
#define LFM_FROM_PLAN 0          /* the first input of the new plan (a usable solve) */
#define LFM_FROM_PREVIOUS_PLAN 1 /* no usable plan: the next input of the last good plan */
#define LFM_FROM_FALLBACK 2      /* the solve failed and no plan was left: the system's
                                    fallback input (fallback_input in lfm_config.c) */

typedef struct {
  int status;          /* of the last solve */
  int success;         /* 1 if status is LFM_SOLVED or LFM_ACCEPTABLE */
  int usable;          /* 1 if success, or the plan's objective is below its warm start's
                          (a solve stopped early: its plan is applied) */
  int action;          /* LFM_FROM_PLAN, LFM_FROM_PREVIOUS_PLAN or LFM_FROM_FALLBACK */
  long iterations;     /* SQP iterations of the last solve (all its starts) */
  double objective;    /* its exact-penalty objective */
  double slack;        /* its total constraint slack (0: every scenario inside) */
  double solve_time;   /* [s] wall time of the last solve */
  double step_time;    /* [s] wall time of the last lfm_controller_step (estimate + solve) */
  long filter_resets;  /* estimator restarts since the last reset (divergence check) */
} lfm_info;

/* A controller initialised with the exported config's numbers; NULL if out of memory.
   Call lfm_controller_reset before the first step. */
lfm_controller* lfm_controller_new(void);

/* Frees it (NULL is fine). */
void lfm_controller_free(lfm_controller* c);

/* A new episode: forgets the estimate, the warm start and the last plan; seed fixes the
   controller's own random draws (the scenarios' latent-force noise). */
void lfm_controller_reset(lfm_controller* c, uint64_t seed);

/* The input u (LFM_NU) for the measurement y (LFM_NX): the agent's whole step, the estimate
   updated with y (the first measurement after a reset starts it), the scenarios built from
   it, the scenario MPC solved, and the first planned input (or, if the solve failed, the
   last plan's next input or the fallback: lfm_info.action). Returns the solve's status,
   LFM_BAD_INPUT for a non-finite y, or LFM_NO_STEP when the agent's estimator is not exported
   (LFM_STEP_AVAILABLE is 0); u is written in every case (the fallback input for the last
   two). */
int lfm_controller_step(lfm_controller* c, const double* y, double* u);

/* The plan (LFM_N, LFM_NU) for the initial state x0 (LFM_NX; every scenario starts there)
   and the latent forces W (LFM_NS, LFM_N, LFM_NW), warm-started from the last plan shifted
   by one step (from zero inputs after a reset); no back-off. Returns the status
   (LFM_BAD_INPUT, with the fallback input at every stage of plan, for a non-finite x0 or W). */
int lfm_controller_solve(lfm_controller* c, const double* x0, const double* W, double* plan);

/* What the last step solved: x0 (LFM_NS, LFM_NX), W (LFM_NS, LFM_N, LFM_NW) and the
   back-off (LFM_N, LFM_NG; zeros for none); any pointer may be NULL. */
void lfm_controller_last_problem(const lfm_controller* c, double* x0, double* W,
                                 double* backoff);

/* The estimate: the mean (LFM_NX + LFM_NP) and covariance (its square) of [x, z]; either
   pointer may be NULL. */
void lfm_controller_estimate(const lfm_controller* c, double* mean, double* cov);

/* The last step's or solve's record. */
lfm_info lfm_controller_info(const lfm_controller* c);

/* The name of a status ("Solve_Succeeded", ...). */
const char* lfm_status_name(int status);

#ifdef __cplusplus
}
#endif

#endif
