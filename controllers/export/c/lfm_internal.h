/* lfm_internal.h: what lfm_controller.c reads of the exported config (lfm_config.c), and the
   entry points of the generated library (lfm_mpc.c) it calls. Not part of the API. */
#ifndef LFM_INTERNAL_H
#define LFM_INTERNAL_H

#include "lfm_config.h"
#include "sqp.h"

#define LFM_D (LFM_NX + LFM_NP) /* the augmented state [x, z] */

enum { LFM_ESTIMATOR_NONE = 0, LFM_ESTIMATOR_UKF = 1, LFM_ESTIMATOR_OTHER = 2 };
enum { LFM_FORECAST_ZERO = 0, LFM_FORECAST_MEAN = 1, LFM_FORECAST_SAMPLED = 2 };

typedef struct {
  lfm_sqp_problem problem;
  lfm_sqp_options options;
  int estimator;                 /* LFM_ESTIMATOR_*: the measurement itself, the UKF, other */
  int forecast;                  /* LFM_FORECAST_*: w = 0, H A^k z, or sampled paths */
  int particles;                 /* 1: scenario starts drawn from the estimate */
  const double* backoff_k;       /* (NG) estimate stds per constraint, or NULL: none */
  const double *A, *Q, *Q_factor, *H; /* latent model (P, P), (P, P), (P, P), (NW, P) */
  const double* process_std;     /* (NX) per-step std of the physical process noise */
  const double* measurement_std; /* (NX) */
  const double* P_inf;           /* (P, P) stationary latent covariance: the prior */
  double divergence_nis;         /* a measurement's NIS above this restarts the estimate */
  const double* fallback_input;  /* (NU) */
  const double* goal;            /* (NX) for lfm_rollout's cost (unused here) */
  const double* weights;         /* (NX, NX) likewise */
} lfm_config;

extern const lfm_config lfm_exported_config;

/* lfm_mpc.c (the generated library's driver, dense.c): the rollout of ns points over n steps,
   the constraint Jacobian of a state, and the symmetric eigen-decomposition. */
int lfm_rollout(long n, long ns, const double* x0T, const double* W, long sa, long sk, long si,
                const double* u, const double* goal, const double* Wq, double* X, double* G,
                double* cost, long nthreads);
int lfm_dense_eigh(long n, const double* M, double* w, double* V);
int lfm_constraint_jacobian(const double* x, double* J);

#endif
